r"""The k-d tree of `lieax.icp` in the native library (`csrc/kdtree.cc`), called through XLA FFI.

The tree is data: `build` makes it from the valid target points in one custom call and returns
it as arrays (`NativeKDTree`), which travel with the index through `jit`, `vmap` and ICP's loop;
the queries (`nearest`, `track`, `spacing`) are custom calls that take those arrays. A compiled
program that holds them is kept by JAX's persistent compilation cache, where one that calls the
host tree of `lieax.icp._host_kdtree` (a Python callback) never is. `neighbours` and
`covariance_entries` (normals, GICP's covariances) build a tree inside their call and query it
with every valid point.

The tree (Friedman, Bentley and Finkel, "An algorithm for finding best matches in logarithmic
expected time", ACM TOMS 1977): each node of more than `LEAF_SIZE` points splits its points'
bounding box at the midpoint of its longest side, one partition pass (the midpoint rule with
boxes shrunk to the points, so that no side is empty: Maneewongvatana and Mount, "It's okay to be
skinny, if your friends are fat", CGC workshop 1999, whose sliding midpoint pykdtree uses; it
builds about 3x faster than median splits, which select rather than partition). A node of
repeated points is a leaf whatever its size. Every leaf holds a point, so `2N - 1` nodes suffice
(`node_capacity`: the arrays' sizes are fixed by the number of points `N`). The points are
stored in tree order, each leaf's contiguous, with their rows. A query descends to the nearer child
first and visits the other only when the squared distance from the query to its cell is below the
current $k$-th best; that distance is kept incrementally, one axis term replaced per level
(Arya and Mount, "Algorithms for fast vector quantization", DCC 1993; the scheme of nanoflann),
from each node's two bounds along its axis: the largest coordinate of the left child and the
smallest of the right one. Distances between points are computed in the points' dtype (as
pykdtree's are), the cell distances in float64; the answers are exact, ties aside.

A batch (leading axes, `vmap`) is one call; the queries of a call are shared with helper threads
when they ask for at least `lieax._threads.PARALLEL_NEIGHBOURS` neighbours in all (lieax's thread
setting, `lieax.set_threads`, caps them), and builds of at least 65536 points in all share their
trees and top subtrees. The helpers sleep between calls, and the calling thread works through the
queries itself, waiting only for those a helper has taken, never for a helper to wake
(`csrc/parallel.h`): on a busy machine, where a woken thread may wait for a time slice, a call
then runs as on one thread, where threads started and joined per call (before December 2026)
made it wait for each of them (issue 31).
"""

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from .. import _native

LEAF_SIZE = 8
# The leaves of the trees that `neighbours` and `covariance_entries` build for their k-nearest
# queries: larger leaves suit more neighbours (GICP's 20 nearest on the scan pairs' targets of 14k,
# 37k and 181k points, one thread: 4-8% less time than leaves of 8).
NEIGHBOURHOOD_LEAF_SIZE = 16
_DTYPES = (np.dtype(np.float32), np.dtype(np.float64))


class NativeKDTree(NamedTuple):
    """The arrays of a tree over `N` points (`C = node_count(N)` nodes), in the points' dtype
    where not said.

    **Fields:**

    - `order`: `(N,)` int32, the row of the points at each tree position, the valid ones first.
    - `points`: `(N, 3)` the points in tree order (`inf` past the valid ones).
    - `nodes`: `(C, 4)` int32 per node: first and end tree positions, the split axis (`-1`: a
      leaf), the right child (the left one follows its parent). Node 0 is the root; its end is
      the number of valid points.
    - `bounds`: `(C, 2)` the left child's largest and the right child's smallest coordinate along
      the split axis.
    - `box`: `(2, 3)` the smallest and largest coordinates of the valid points.
    """

    order: jax.Array
    points: jax.Array
    nodes: jax.Array
    bounds: jax.Array
    box: jax.Array


def node_capacity(n):
    """The nodes the tree of `n` points may need, `2n - 1` (every leaf holds a point; 1 for
    none)."""
    return max(1, 2 * n - 1)


def supports(dtype) -> bool:
    """Whether the native tree takes points of `dtype` (float32 and float64)."""
    return np.dtype(dtype) in _DTYPES


def _call(target, results, *args, **attributes):
    if _native.library() is None:  # (loads and registers the targets on first use)
        raise RuntimeError("the native library is not available (lieax._native.available()).")
    return jax.ffi.ffi_call(target, results, vmap_method="expand_dims")(*args, **attributes)


def build(points, valid) -> NativeKDTree:
    """The tree of the rows of `points` `(n, 3)` (float32 or float64) where `valid` `(n,)` and
    finite; one custom call."""
    n, dtype = points.shape[0], points.dtype
    capacity = node_capacity(n)
    results = (
        jax.ShapeDtypeStruct((n,), jnp.int32),
        jax.ShapeDtypeStruct((n, 3), dtype),
        jax.ShapeDtypeStruct((capacity, 4), jnp.int32),
        jax.ShapeDtypeStruct((capacity, 2), dtype),
        jax.ShapeDtypeStruct((2, 3), dtype),
    )
    arrays = _call("lieax_kdtree_build", results, points, valid, leaf_size=np.int64(LEAF_SIZE))
    return NativeKDTree(*arrays)


def nearest(tree: NativeKDTree, queries, radius, active):
    """The nearest valid point within `radius` (inclusive) of each query `(m, 3)` where `active`:
    `(row, squared_distance)`, row 0 and `inf` where there is none (queries in the tree's
    dtype)."""
    m, dtype = queries.shape[0], tree.points.dtype
    results = (jax.ShapeDtypeStruct((m,), jnp.int32), jax.ShapeDtypeStruct((m,), dtype))
    return _call(
        "lieax_kdtree_nearest", results, *tree, queries.astype(dtype),
        jnp.asarray(radius, dtype), active,
    )  # fmt: skip


def track(tree: NativeKDTree, queries, radius, active, pairs):
    """`lieax.icp._host_kdtree.track_in_kdtree`'s query: for each active query, the row of its
    nearest valid point within twice `radius` (`-1` for none) and its allowance,
    $(\\min(d_2, 2r) - d_1)/2$ when `pairs` (a scalar bool) asks for the second-nearest distance
    $d_2$, else 0 ($r$ for none; `-inf` for queries not active)."""
    m, dtype = queries.shape[0], tree.points.dtype
    results = (jax.ShapeDtypeStruct((m,), jnp.int32), jax.ShapeDtypeStruct((m,), dtype))
    return _call(
        "lieax_kdtree_track", results, *tree, queries.astype(dtype), jnp.asarray(radius, dtype),
        active, jnp.asarray(pairs, bool),
    )  # fmt: skip


def spacing(tree: NativeKDTree):
    """`(N,)` the distance from each valid point to its nearest other valid point (`inf` for a
    single one, 0 for invalid rows), in the original row order."""
    result = jax.ShapeDtypeStruct(tree.order.shape, tree.points.dtype)
    return _call("lieax_kdtree_spacing", result, *tree)


def neighbours(points, valid, k):
    """`(n, k)` int32: the `k` nearest valid rows of each valid row of `points` `(n, 3)`, itself
    among them, nearest first; `-1` where there are fewer valid rows and in rows not `valid`."""
    result = jax.ShapeDtypeStruct((points.shape[0], k), jnp.int32)
    return _call(
        "lieax_kdtree_neighbours", result, points, valid,
        leaf_size=np.int64(NEIGHBOURHOOD_LEAF_SIZE),
    )  # fmt: skip


def covariance_entries(points, valid, k):
    r"""`(n, 6)` the upper entries `(00, 01, 02, 11, 12, 22)` of the sample covariance of each
    valid row and its `k - 1` nearest valid rows, $\frac1c \sum_j o_j o_j^\top - \bar o \bar
    o^\top$ with the offsets $o_j = p_j - p$ (small_gicp's sums), in float64 then the points'
    dtype; 0 in rows not `valid`."""
    result = jax.ShapeDtypeStruct((points.shape[0], 6), points.dtype)
    return _call(
        "lieax_kdtree_covariances", result, points, valid, k=np.int64(k),
        leaf_size=np.int64(NEIGHBOURHOOD_LEAF_SIZE),
    )  # fmt: skip
