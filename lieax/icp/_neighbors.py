r"""The k-nearest-neighbour graph of a point cloud under `jit` with fixed shapes: the
neighbourhoods of `estimate_normals` and `estimate_covariances` off the CPU, where there is no
k-d tree to call (`search="graph"` of those functions).

The points are sorted into a k-d tree of `2**L` equal leaves (`lieax.icp._kd_order`, slots in leaf
order; padding and masked points marked invalid); a beam search down the tree's node boxes finds
the `adjacent_leaves` leaves nearest each leaf, and each point's `degree` nearest neighbours are
selected among their points (exact where the neighbourhood lies inside those leaves: 99.96% of the
bunny's 20-neighbourhoods with 16 leaves of 16 points).

Why this shape: on the CPU, XLA's `top_k` and sorts are slow (tens of ns per element), so the
nearest candidates are selected with a compare-exchange network over packed keys.
"""

import math
from typing import NamedTuple

import jax
import jax.numpy as jnp

from ._coordinates import squared_norms
from ._kd_order import kd_order, tree_shape

_MAX_INDEX_BITS = 24  # 2**24 points at most: the kd sort packs an 8-bit key with the position


class NeighborIndex(NamedTuple):
    """A point cloud's neighbour graph (see the module docstring). Shapes: `N = leaves * B`
    slots, `D = degree`.

    **Fields:**

    - `points`: `(N, 3)` the points in leaf order; invalid slots hold `inf`.
    - `order`: `(N,)` int32, the index in the original cloud of each slot (0 for invalid slots).
    - `valid`: `(N,)` bool.
    - `graph`: `(N, D)` int32, the slots of each point's nearest neighbours (itself excluded).
    - `graph_points`: `(N, 3, D)` their coordinates, coordinate-major.
    """

    points: jax.Array
    order: jax.Array
    valid: jax.Array
    graph: jax.Array
    graph_points: jax.Array


def build_index(points, mask=None, *, leaf_size=16, degree=8, adjacent_leaves=16) -> NeighborIndex:
    """The neighbour graph of `points` (shape `(n, 3)`); runs under `jit` and `vmap`.

    **Arguments:**

    - `points`: the cloud. Rows where `mask` is False are ignored (padding).
    - `leaf_size`: largest number of points per leaf of the tree.
    - `degree`: nearest neighbours per point.
    - `adjacent_leaves`: leaves searched around each leaf.

    **Returns:** a `NeighborIndex`.
    """
    points = jnp.asarray(points)
    n = points.shape[0]
    if n >= 2**_MAX_INDEX_BITS:
        raise ValueError(f"build_index handles fewer than {2**_MAX_INDEX_BITS} points, got {n}.")
    valid = jnp.ones((n,), bool) if mask is None else jnp.asarray(mask, bool)
    depth, size = tree_shape(n, leaf_size)
    slots = size * 2**depth
    pad = slots - n
    points = jnp.where(valid[:, None], points, jnp.inf)
    points = jnp.concatenate([points, jnp.full((pad, 3), jnp.inf, points.dtype)])
    valid = jnp.concatenate([valid, jnp.zeros((pad,), bool)])
    points, valid, order = kd_order(points, valid, depth, size)

    leaves = 2**depth
    blocks = points.reshape(leaves, size, 3)
    block_valid = valid.reshape(leaves, size, 1)
    leaf_lo = jnp.min(jnp.where(block_valid, blocks, jnp.inf), axis=1)
    leaf_hi = jnp.max(jnp.where(block_valid, blocks, -jnp.inf), axis=1)
    # Every node's box in one scatter: leaf j lies under node 2**l - 1 + (j >> (depth - l)).
    levels = jnp.arange(depth + 1, dtype=jnp.int32)
    ancestors = (2**levels - 1) + (jnp.arange(leaves, dtype=jnp.int32)[:, None] >> (depth - levels))
    node_lo = jax.ops.segment_min(
        jnp.repeat(leaf_lo, depth + 1, axis=0), ancestors.reshape(-1), 2 * leaves - 1
    )
    node_hi = jax.ops.segment_max(
        jnp.repeat(leaf_hi, depth + 1, axis=0), ancestors.reshape(-1), 2 * leaves - 1
    )
    adjacent = _beam(
        node_lo, node_hi, leaf_lo, leaf_hi, depth, min(adjacent_leaves, leaves),
        own_leaf=jnp.arange(leaves, dtype=jnp.int32),
    )  # fmt: skip
    graph = _neighbor_graph(points, valid, adjacent, size, degree)
    graph_points = jnp.transpose(points[graph], (0, 2, 1))
    return NeighborIndex(points, order, valid, graph, graph_points)


def _box_distance_squared(lo_a, hi_a, lo_b, hi_b):
    gap = jnp.maximum(jnp.maximum(lo_b - hi_a, lo_a - hi_b), 0.0)
    gap = jnp.where(jnp.isnan(gap), jnp.inf, gap)
    return squared_norms(gap)


def _select_smallest(values, count):
    """Column indices of the `count` smallest entries of each row of `values` (ties, and near-ties
    within a relative 2**-(23 - column bits), in any order).

    Keys pack the value's float32 bits with the column index into one int32; a compare-exchange
    insertion network keeps the `count` smallest keys of each row in registers while the columns
    stream past (XLA's `top_k` and sorts are several times slower on the CPU).
    """
    columns = values.shape[-1]
    count = min(count, columns)
    bits = max(1, math.ceil(math.log2(columns)))
    as_float32 = jnp.minimum(values, jnp.finfo(jnp.float32).max).astype(jnp.float32)
    as_float32 = jnp.where(values == jnp.inf, jnp.inf, as_float32)
    key = jax.lax.bitcast_convert_type(as_float32, jnp.int32)
    key = (key >> bits << bits) | jnp.arange(columns, dtype=jnp.int32)
    key = jnp.moveaxis(key, -1, 0)  # columns first: one row of keys per step
    largest = jnp.iinfo(jnp.int32).max

    def insert(column, best):
        x = key[column]
        kept = []
        for b in best:
            kept.append(jnp.minimum(b, x))
            x = jnp.maximum(b, x)
        return tuple(kept)

    start = tuple(jnp.full(key.shape[1:], largest, jnp.int32) for _ in range(count))
    best = jax.lax.fori_loop(0, columns, insert, start)
    return jnp.stack(best, axis=-1) & (2**bits - 1)


def _beam(node_lo, node_hi, query_lo, query_hi, depth, width, own_leaf=None):
    """The `width` leaves nearest to each query box (a point when `lo == hi`), by a beam search
    down the tree: at every level keep the `width` nearest children of the nodes kept above.

    `own_leaf` forces each query's own leaf (and its ancestors) into the beam.

    **Returns:** `(m, width)` int32 leaves, `-1` where fewer exist.
    """
    m = query_lo.shape[0]
    candidates = jnp.full((m, width), -1, jnp.int32).at[:, 0].set(0)

    def level(here, candidates):
        children = jnp.concatenate([2 * candidates, 2 * candidates + 1], axis=1)
        children = jnp.where(jnp.concatenate([candidates, candidates], axis=1) >= 0, children, -1)
        heap = jnp.where(children >= 0, (2 << here) - 1 + children, 0)
        d2 = _box_distance_squared(
            query_lo[:, None], query_hi[:, None], node_lo[heap], node_hi[heap]
        )
        d2 = jnp.where(children >= 0, d2, jnp.inf)
        if own_leaf is not None:
            ancestor = own_leaf >> (depth - 1 - here)
            d2 = jnp.where(children == ancestor[:, None], -1.0, d2)
        chosen = _select_smallest(d2, width)
        kept = jnp.take_along_axis(children, chosen, axis=1)
        kept_d2 = jnp.take_along_axis(d2, chosen, axis=1)
        kept = jnp.where(kept_d2 < jnp.inf, kept, -1)
        return kept

    return jax.lax.fori_loop(0, depth, level, candidates)


def _neighbor_graph(points, valid, adjacent, size, degree):
    """Each point's `degree` nearest among the points of its leaf's `adjacent` leaves, `(slots,
    degree)` slots (the first repeated where fewer exist)."""
    leaves, count = adjacent.shape
    slots = points.shape[0]
    own = points.reshape(leaves, size, 3)
    candidate_slots = adjacent[:, :, None] * size + jnp.arange(size, dtype=jnp.int32)
    candidate_slots = jnp.where(adjacent[:, :, None] >= 0, candidate_slots, 0).reshape(
        leaves, count * size
    )
    present = jnp.repeat(adjacent >= 0, size, axis=1)
    candidates = jnp.where(
        present[..., None], points[candidate_slots], jnp.inf
    )  # (leaves, count * size, 3)
    d2 = sum(
        (own[:, :, None, axis] - candidates[:, None, :, axis]) ** 2 for axis in range(3)
    )  # (leaves, size, count * size)
    own_slot = jnp.arange(slots, dtype=jnp.int32).reshape(leaves, size)
    d2 = jnp.where(own_slot[..., None] == candidate_slots[:, None, :], jnp.inf, d2)
    d2 = jnp.where(jnp.isnan(d2), jnp.inf, d2)
    degree_here = min(degree, count * size)
    columns = _select_smallest(d2, degree_here)
    graph = jnp.take_along_axis(
        jnp.broadcast_to(candidate_slots[:, None, :], d2.shape), columns, axis=2
    ).reshape(slots, degree_here)
    if degree_here < degree:
        graph = jnp.concatenate([graph, jnp.repeat(graph[:, :1], degree - degree_here, 1)], 1)
    return graph
