r"""The k-d tree search of `lieax.icp` (`search="kdtree"`): `KDTreeIndex`, its build and queries,
served by the native library's tree or, without it, by a tree on the host.

On a CPU a compiled k-d tree answers a nearest-neighbour query in well under a microsecond,
faster than any fixed-shape search XLA compiles (see `benchmarks/neighbors.py`). Two kinds serve
the same functions here, chosen by `build_kdtree(library=...)` (default `default_library`):

- `"native"` (`lieax.icp._native_kdtree`): the tree is arrays built by one custom call and
  carried in `KDTreeIndex.tree`; the queries are custom calls on them. Pure (no state outside
  the arrays), one call per batch under `vmap`, and the programs are kept by JAX's persistent
  compilation cache. Its answers are pykdtree's, ties aside (`tests/test_native_kdtree.py`).
- `"pykdtree"` or `"scipy"`: the fallback where the native library is not available. The trees
  of pykdtree and SciPy's `cKDTree` live on the host, and `lieax._host_call.host_call` hands
  XLA's host buffers to NumPy in a few microseconds (a program with such a callback is compiled
  in every process):

  - `build_kdtree` sends the target to the host once; the host builds the tree over its valid
    points and keeps it in a registry, keyed by a digest of the points and mask (a second build
    of the same target, or every element of a `vmap` that shares a target, reuses it), and hands
    back an integer id that travels in the traced `KDTreeIndex`;
  - `nearest_in_kdtree` sends the queries and the id each time, and gets the nearest valid target
    point within the radius back (under `vmap`, one host call for the whole batch, with one tree
    query per target: `_per_target`).

Warm starts. ICP's iterations use `track_in_kdtree`, which keeps the answer of a query that moved
less than half the gap between its nearest and second-nearest distances (see there), and asks the
tree for the second-nearest distance only when the moves are small enough for that to pay.
For `nearest_in_kdtree(previous=...)` the host tree also computes, on the first such call, each
target point's `spacing` (`kdtree_spacing`), the distance to its nearest other valid point, and
keeps it with the tree (a k-nearest query over the whole target, 0.2-0.4 s with pykdtree on the
Kinect benchmark's 181k points, that ICP's `track_in_kdtree` does not need, so the build does
not pay for it). The native tree keeps nothing between calls, so it would pay that query in
every call, more than the queries it saves: it answers every query and ignores `previous`
(`kdtree_spacing` still gives its spacing). A query at distance $d$ from its previous match $c$ keeps it
when $2d \le$ `spacing[c]`: every other point $p$ has $|q - p| \ge |p - c| - d \ge$
`spacing[c]` $- d \ge d$ (the triangle inequality), so $c$ is still the nearest. Only the other
queries are sent to the tree (40-80% of the source points are kept near convergence on the
benchmark's scans).

The registry keeps the `_CAPACITY` most recently used host trees; a query for an evicted tree
raises. Both kinds need the data on the host: on another backend (a GPU) it raises, naming the
backends that run there (`"grid"`, `"brute"`).
"""

import collections
import functools
import hashlib
import threading
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from .. import _native, _threads
from .._host_call import host_call
from . import _native_kdtree
from ._coordinates import row_sums, squared_norms

_CAPACITY = 256
# id -> [digest, tree, dtype, kept, spacing (filled by the first `kdtree_spacing` call)]
_TREES: collections.OrderedDict = collections.OrderedDict()
_IDS: dict = {}  # digest -> id
_NEXT_ID = [0]
_LOCK = threading.Lock()
_LIBRARIES = ("native", "scipy", "pykdtree")


class KDTreeIndex(NamedTuple):
    """A target cloud and its k-d tree (see the module docstring).

    **Fields:**

    - `points`: `(N, 3)` the target points in their original order; invalid points hold `inf`.
    - `order`: `(N,)` int32, `arange(N)` (slots are the original indices).
    - `valid`: `(N,)` bool.
    - `tree`: the native tree's arrays (a `lieax.icp._native_kdtree.NativeKDTree`), or for the
      host trees `()` int32, the id of the tree in the host registry.
    """

    points: jax.Array
    order: jax.Array
    valid: jax.Array
    tree: jax.Array | _native_kdtree.NativeKDTree


def check_on_host(points, what):
    platforms = (
        {jax.default_backend()}
        if isinstance(points, jax.core.Tracer) or not isinstance(points, jax.Array)
        else {device.platform for device in points.devices()}
    )
    if platforms != {"cpu"}:
        raise ValueError(
            f"search='kdtree' runs on the host CPU, but {what} lives on {sorted(platforms)}: use "
            "search='grid' or search='brute' there (or move the data to the CPU)."
        )


def build_kdtree(points, mask=None, *, library=None) -> KDTreeIndex:
    """Build (or find in the host registry) the k-d tree of `points` (shape `(n, 3)`, rows where
    `mask` is False ignored); runs under `jit` and `vmap`.

    **Arguments:**

    - `points`, `mask`: the target cloud and its valid rows.
    - `library`: `"native"` (the native library's tree, `lieax.icp._native_kdtree`: float32 and
      float64 points), `"scipy"` (`scipy.spatial.cKDTree`) or `"pykdtree"` (needs the package;
      both on the host, see `host_tree`); default `default_library(points.dtype)`.

    **Returns:** a `KDTreeIndex`.
    """
    points = jnp.asarray(points)
    if library is None:
        library = default_library(points.dtype)
    if library not in _LIBRARIES:
        raise ValueError(f"library must be one of {_LIBRARIES}, got {library!r}.")
    if library == "pykdtree":
        import pykdtree.kdtree  # noqa: F401  (fail here, at trace time, when it is missing)
    if library == "native":
        _check_native(points.dtype)
    else:
        _threads.prepare()  # (the thread pools listed here, not in the callbacks)
    check_on_host(points, "the target")
    n = points.shape[0]
    if n >= 2**24:
        raise ValueError(f"search='kdtree' handles fewer than {2**24} points, got {n}.")
    valid = jnp.ones((n,), bool) if mask is None else jnp.asarray(mask, bool)
    valid = valid & jnp.all(jnp.isfinite(points), axis=1)
    if library == "native":
        tree = _native_kdtree.build(points, valid)
    else:
        tree = host_call(_BUILDERS[library], jax.ShapeDtypeStruct((), jnp.int32), points, valid)
    points = jnp.where(valid[:, None], points, jnp.inf)
    return KDTreeIndex(points, jnp.arange(n, dtype=jnp.int32), valid, tree)


def has_pykdtree():
    try:
        import pykdtree.kdtree  # noqa: F401
    except ImportError:
        return False
    return True


def default_library(dtype=None):
    """`"native"` where the native library is available (`lieax._native.available()`) and takes
    `dtype` (float32, float64; `None`: any), else the host trees: `"pykdtree"` where it is
    installed (it builds 2-4x and queries up to 2x faster than cKDTree on the benchmark's clouds,
    `benchmarks/neighbors.py`), else `"scipy"`."""
    if _native.available() and (dtype is None or _native_kdtree.supports(dtype)):
        return "native"
    return host_library()


def host_library():
    """The host tree: `"pykdtree"` where it is installed, else `"scipy"`."""
    return "pykdtree" if has_pykdtree() else "scipy"


def _check_native(dtype):
    if not _native.available():
        raise ValueError(
            "library='native' needs the native library (lieax._native: not built, or turned off "
            "by LIEAX_NATIVE=0); use 'pykdtree' or 'scipy'."
        )
    if not _native_kdtree.supports(dtype):
        raise ValueError(
            f"library='native' takes float32 or float64 points, got {np.dtype(dtype)}; use "
            "'pykdtree' or 'scipy'."
        )


def is_native(index: KDTreeIndex) -> bool:
    """Whether `index` holds the native tree (else a host tree's id)."""
    return isinstance(index.tree, _native_kdtree.NativeKDTree)


def host_tree(points, library=None):
    """The k-d tree of `points` (a C-contiguous `(n, 3)` NumPy array, `n >= 1`) on the host:
    pykdtree's `KDTree` or SciPy's `cKDTree` (`library`, default `host_library()`).

    SciPy's tree is built with `balanced_tree=False`: XLA runs host callbacks with the x86
    flush-to-zero and denormals-are-zero flags set (MXCSR `0x9fe2`), and under those flags SciPy
    1.17's default build (`balanced_tree=True`, `compact_nodes=True`) segfaults on a cloud with
    repeated points, inside JAX or not (`tests/test_icp_search.py`); either flag off builds."""
    if (library or host_library()) == "pykdtree":
        from pykdtree.kdtree import KDTree

        return KDTree(points)
    from scipy.spatial import cKDTree

    return cKDTree(points, balanced_tree=False)


def tree_query(tree, queries, k, **options):
    """`tree.query(queries, k, **options)` on one OpenMP thread (pykdtree's) below
    `lieax._threads.PARALLEL_NEIGHBOURS` neighbours asked for, else on lieax's thread setting
    (`lieax.set_threads`), the calling thread's count restored after it."""
    threads = _threads.threads_for(queries.shape[0] * k, _threads.PARALLEL_NEIGHBOURS)
    with _threads.openmp_limited(threads):
        return tree.query(queries, k, **options)


def valid_row_neighbours(points, valid, k, library=None):
    """The valid rows of `points` `(n, 3)` and their neighbourhoods among themselves (NumPy, on
    the host; one `host_tree` (`library`) of the valid rows): `(rows, cloud, nearest)` with
    `rows` `(m,)` their indices, `cloud` `(m, 3)` their points (contiguous) and `nearest`
    `(m, min(k, m))` the nearest valid rows of each, itself among them, nearest first, as indices
    into `rows`; `cloud` and `nearest` are `None` when no row is valid."""
    rows = np.flatnonzero(valid)
    if rows.size == 0:
        return rows, None, None
    count = min(k, rows.size)
    every = rows.size == points.shape[0]  # (no gather of the rows: the usual case)
    cloud = np.ascontiguousarray(points if every else points[rows])
    _, nearest = tree_query(host_tree(cloud, library), cloud, count)
    return rows, cloud, np.asarray(nearest, np.intp).reshape(rows.size, count)


def nearest_valid_rows(points, valid, k, library=None):
    """The `k` nearest valid rows of every valid row of `points` `(n, 3)` (itself among them;
    NumPy, on the host), `(n, k)` int32 row indices nearest first, `-1` where there are fewer
    valid rows and in the rows not `valid` (`valid_row_neighbours`)."""
    found = np.full((points.shape[0], k), -1, np.int32)
    rows, _, nearest = valid_row_neighbours(points, valid, k, library)
    if nearest is not None:
        found[rows, : nearest.shape[1]] = rows[nearest]
    return found


def _register(library, points, valid):
    digest = hashlib.blake2b(
        library.encode() + str(points.dtype).encode() + points.tobytes() + valid.tobytes(),
        digest_size=16,
    ).digest()
    with _LOCK:
        tree_id = _IDS.get(digest)
        if tree_id is not None and tree_id in _TREES:
            _TREES.move_to_end(tree_id)
            return np.int32(tree_id)
    kept = np.flatnonzero(valid)
    tree = host_tree(np.ascontiguousarray(points[kept]), library) if kept.size else None
    with _LOCK:
        tree_id = _NEXT_ID[0] % 2**31
        _NEXT_ID[0] += 1
        _IDS[digest] = tree_id
        _TREES[tree_id] = [digest, tree, points.dtype, kept, None]
        while len(_TREES) > _CAPACITY:
            _, (old_digest, *_) = _TREES.popitem(last=False)
            _IDS.pop(old_digest, None)
    return np.int32(tree_id)


# The host sides of `build_kdtree`, one per library (module-level, so that traces see one function).
_BUILDERS = {library: functools.partial(_register, library) for library in _LIBRARIES}


def _entry(tree_id):
    with _LOCK:
        entry = _TREES.get(int(tree_id))
    if entry is None:
        raise RuntimeError(
            f"the host k-d tree {int(tree_id)} was evicted (more than {_CAPACITY} targets in use "
            "at once): build the index again."
        )
    return entry


def kdtree_spacing(index: KDTreeIndex):
    """`(N,)` the distance from each valid point of the index to its nearest other valid point
    (`inf` for a single point, 0 for invalid ones); one host call, the k-nearest query made on
    the first call for this tree only (the host keeps the result with the tree); for the native
    tree, one custom call that makes the query (XLA computes it once per program)."""
    points = index.points
    if is_native(index):
        return _native_kdtree.spacing(index.tree)
    return host_call(
        _spacing, jax.ShapeDtypeStruct(points.shape[:1], points.dtype), index.tree, points
    )


def _spacing(tree_id, points):
    """Host side of `kdtree_spacing` (`points` the index's, `inf` in invalid rows)."""
    entry = _entry(tree_id)
    _, tree, dtype, kept, spacing = entry
    if spacing is None:
        spacing = np.zeros(points.shape[:1], points.dtype)
        if kept.size == 1:
            spacing[kept] = np.inf
        elif kept.size > 1:
            d, _ = tree_query(tree, np.ascontiguousarray(points[kept], dtype), 2)
            spacing[kept] = d[:, 1]
        entry[4] = spacing
    return spacing


def _query(tree_id, queries, radius, active):
    """Host side of `nearest_in_kdtree`: `(m, 2)` rows of (squared distance, slot)."""
    _, tree, dtype, kept, _ = _entry(tree_id)
    m = queries.shape[0]
    out = np.empty((m, 2), queries.dtype)
    out[:, 0], out[:, 1] = np.inf, 0
    rows = np.flatnonzero(active)
    if tree is None or rows.size == 0:
        return out
    # Both libraries test `d < bound`: widen the bound by rounding, filter `d <= radius` below.
    bound = float(radius) * (1 + 8 * np.finfo(queries.dtype).eps)
    d, i = tree_query(
        tree, np.ascontiguousarray(queries[rows], dtype), 1, distance_upper_bound=bound
    )
    found = np.isfinite(d) & (d <= radius)
    hit = rows[found]
    out[hit, 0] = np.square(d[found], dtype=np.float64)
    out[hit, 1] = kept[i[found]]
    return out


def nearest_in_kdtree(index: KDTreeIndex, queries, radius=jnp.inf, *, mask=None, previous=None):
    """The nearest valid target point within `radius` (inclusive) of each query, exact (up to
    ties), or none; one host call.

    **Arguments:**

    - `index`: from `build_kdtree`.
    - `queries`: shape `(m, 3)`.
    - `radius`: the search radius (`inf`: the nearest point).
    - `mask`: queries to skip (they get no match).
    - `previous`: `(m,)` slots of earlier matches (any valid slots): a query whose earlier match
      is provably still its nearest (see the module docstring) is not sent to the host tree
      (the native tree answers every query: see there).

    **Returns:** `(slot, squared_distance)`: the match's index in the target (0 where there is
    none) and its squared distance (`inf` where there is none).
    """
    queries = jnp.asarray(queries)
    check_on_host(queries, "the queries")
    m = queries.shape[0]
    active = jnp.ones((m,), bool) if mask is None else jnp.asarray(mask, bool)
    active = active & jnp.all(jnp.isfinite(queries), axis=1)
    radius = jnp.asarray(radius, queries.dtype)
    kept = jnp.zeros((m,), bool)
    if is_native(index):
        previous = None
    if previous is not None:
        previous_d2 = squared_norms(index.points[previous].astype(queries.dtype) - queries)
        spacing = kdtree_spacing(index)[previous].astype(queries.dtype)
        slack = 4 * (1 + 16 * jnp.finfo(queries.dtype).eps)  # rounding of both sides
        kept = active & index.valid[previous] & (slack * previous_d2 <= spacing * spacing)
    if is_native(index):
        slot, d2 = _native_kdtree.nearest(index.tree, queries, radius, active & ~kept)
        d2 = d2.astype(queries.dtype)
    else:
        out = host_call(
            _query, jax.ShapeDtypeStruct((m, 2), queries.dtype), index.tree, queries, radius,
            active & ~kept, batched=_per_target(_query),
        )  # fmt: skip
        # A slot below 2**24 is exact in float32.
        slot, d2 = out[:, 1].astype(jnp.int32), out[:, 0]
    if previous is not None:
        hit = kept & (previous_d2 <= radius * radius)
        slot = jnp.where(hit, previous, jnp.where(kept, 0, slot))
        d2 = jnp.where(hit, previous_d2, jnp.where(kept, jnp.inf, d2))
    return slot, d2


class KDTreeWarmStart(NamedTuple):
    r"""What `track_in_kdtree` knows from its last call, per query (ICP carries it through its
    iterations).

    **Fields:**

    - `queries`: `(m, 3)` where each query was last sent to the tree.
    - `slot`: `(m,)` int32, its nearest valid target point there, `-1` for none within twice
      the radius.
    - `allowance`: `(m,)` how far the query may move from `queries` with that answer standing:
      $(\min(d_2, 2r) - d_1)/2$ for nearest and second-nearest distances $d_1, d_2$ (0 when
      only the nearest was asked for), $r$ for none within $2r$, `-inf` before the first call.
    - `gap`: `()` the mean allowance of the queries that found a point in the last call that
      asked for two neighbours (`inf` before the first).
    """

    queries: jax.Array
    slot: jax.Array
    allowance: jax.Array
    gap: jax.Array


def cold_start(m, dtype) -> KDTreeWarmStart:
    """A `KDTreeWarmStart` for `m` queries that keeps nothing (every query goes to the tree)."""
    return KDTreeWarmStart(
        jnp.zeros((m, 3), dtype),
        jnp.full((m,), -1, jnp.int32),
        jnp.full((m,), -jnp.inf, dtype),
        jnp.asarray(jnp.inf, dtype),
    )


# `track_in_kdtree` asks for two neighbours when at least this share of the queries it sends moved
# less than the last mean allowance (`KDTreeWarmStart.gap`).
_PAIR_SHARE = 0.1


def track_in_kdtree(index: KDTreeIndex, queries, radius, warm: KDTreeWarmStart, *, mask=None):
    r"""`nearest_in_kdtree` for queries that move a little between calls (ICP's iterations):
    exact (up to ties), sending to the host only the queries whose last answer may have changed.

    A query $q$ whose nearest point $c$ lay at $d_1$ and every other point at least
    $d_2' = \min(d_2, 2r)$ away, now at $q'$ with $\delta = |q' - q|$, still has $c$ nearest when
    $\delta < (d_2' - d_1)/2$: $|q' - c| \le d_1 + \delta < d_2' - \delta \le |q' - p|$ for every
    other $p$ (the triangle inequality). A query with no point within $2r$ still has none within
    $r$ when $\delta < r$. (Slack for rounding: 16 ulps of the largest coordinate.) Near
    convergence the steps are tiny and almost every query is kept, where the spacing test of
    `nearest_in_kdtree(previous=...)` keeps 40-80%.

    The second-nearest distance only serves the next call, and costs: a query for one neighbour
    is about 28% cheaper (pykdtree on the benchmark's scans). While the queries move far (ICP's
    first iterations), an allowance would not be used, so the tree is asked for the nearest
    point within $r$ alone (exact all the same; the allowance of a match, or of none, is then 0;
    a query far from the target stops early, not looking for its nearest point out to $2r$:
    point-to-plane on `benchmarks/icp.py`'s Kinect and bunny pairs 3-18% faster, December 2026).
    It is asked for two when at least `_PAIR_SHARE` of the queries sent moved less
    than `gap`, the mean allowance of the last call that asked for two: the moves have become
    small enough for many answers to stand in the next call. (Replayed on the ICP iterates of the
    benchmark's LiDAR, Kinect and full bunny pairs: 32-37% fewer neighbours asked for than always
    asking for two, about the same queries kept near convergence. A share of 0.1 rather than 0.3
    switches one iteration earlier on the full bunny, 8% less tree work there, and leaves the
    2 mm bunny, the LiDAR and the Kinect pairs within 1%, counting a query for two neighbours
    as 1.3-1.6 queries for one; 0.02 costs 15% more on the LiDAR pair.)

    **Returns:** `(slot, squared_distance, warm)`: the match's index in the target (0 where there
    is none), its squared distance (`inf` where there is none, or beyond `radius`), and the
    `KDTreeWarmStart` for the next call.
    """
    queries = jnp.asarray(queries)
    check_on_host(queries, "the queries")
    m, dtype = queries.shape[0], queries.dtype
    active = jnp.ones((m,), bool) if mask is None else jnp.asarray(mask, bool)
    active = active & jnp.all(jnp.isfinite(queries), axis=1)
    radius = jnp.asarray(radius, dtype)
    moved = jnp.sqrt(squared_norms(queries - warm.queries))
    # (the largest coordinate of each row first: the reduction then reads an (m,) array, not a
    # materialized (m, 3) one)
    largest = jnp.maximum(
        jnp.maximum(jnp.abs(queries[:, 0]), jnp.abs(queries[:, 1])), jnp.abs(queries[:, 2])
    )
    scale = jnp.max(jnp.where(active, largest, 0.0))
    slack = 16 * jnp.finfo(dtype).eps * scale
    kept = active & (moved + slack < warm.allowance.astype(dtype))
    sent = active & ~kept
    gap = warm.gap.astype(dtype)

    near, total = row_sums([(sent & (moved < gap)).astype(dtype), sent.astype(dtype)])
    pairs = near >= _PAIR_SHARE * total
    if is_native(index):
        fresh_slot, fresh_allowance = _native_kdtree.track(index.tree, queries, radius, sent, pairs)
        fresh_allowance = fresh_allowance.astype(dtype)
    else:
        out = host_call(
            _track_query, jax.ShapeDtypeStruct((m, 2), dtype), index.tree, queries, radius, sent,
            pairs, batched=_per_target(_track_query),
        )  # fmt: skip
        fresh_slot, fresh_allowance = out[:, 0].astype(jnp.int32), out[:, 1]  # (slots < 2**24)
    fresh_hits = sent & (fresh_slot >= 0)
    hits, allowances = row_sums(
        [fresh_hits.astype(dtype), jnp.where(fresh_hits, fresh_allowance, 0.0)]
    )
    mean = allowances / jnp.maximum(hits, 1)
    gap = jnp.where(pairs & (hits > 0), mean.astype(dtype), gap)
    nearest = jnp.where(kept, warm.slot, fresh_slot)
    allowance = jnp.where(kept, warm.allowance.astype(dtype), fresh_allowance)
    reference = jnp.where(kept[:, None], warm.queries.astype(dtype), queries)
    found = active & (nearest >= 0)
    slot = jnp.where(found, nearest, 0)
    d2 = squared_norms(index.points[slot].astype(dtype) - queries)
    d2 = jnp.where(found & (d2 <= radius * radius), d2, jnp.inf)
    return slot, d2, KDTreeWarmStart(reference, nearest, allowance, gap)


def _per_target(host):
    """`host(tree_id, queries (m, 3), radius, active (m,), *flags)` -> `(m, c)` for a batch (the
    `batched` of `host_call`, under `vmap`): `(B, m, c)`. Elements that share a tree, radius and
    flags (a batch of starts for one target) send their queries in one tree query: one pass of
    pykdtree's threads over them all, where a call per element pays the host call and the threads'
    start-up `B` times."""

    def batched(tree_ids, queries, radii, active, *flags):
        keys = np.stack([np.asarray(x, np.float64) for x in (tree_ids, radii, *flags)], axis=1)
        _, element_group = np.unique(keys, axis=0, return_inverse=True)
        element_group = element_group.reshape(-1)
        out = None
        for group in range(element_group.max() + 1):
            members = np.flatnonzero(element_group == group)
            first = members[0]
            flat = host(
                tree_ids[first], queries[members].reshape(-1, 3), radii[first],
                active[members].reshape(-1), *(f[first] for f in flags),
            )  # fmt: skip
            if out is None:
                out = np.empty((*queries.shape[:2], flat.shape[-1]), flat.dtype)
            out[members] = flat.reshape(members.size, queries.shape[1], -1)
        return out

    return batched


def _track_query(tree_id, queries, radius, active, pairs):
    """Host side of `track_in_kdtree`: `(m, 2)` rows of (slot or -1, allowance); rows not
    `active` get (-1, -inf); `pairs` False asks the tree for the nearest point within the radius
    only (the allowance of a match, or of none, is then 0)."""
    _, tree, dtype, kept, _ = _entry(tree_id)
    m = queries.shape[0]
    out = np.empty((m, 2), queries.dtype)
    out[:, 0], out[:, 1] = -1, -np.inf
    rows = np.flatnonzero(active)
    if rows.size == 0:
        return out
    reach = 2 * float(radius)
    if tree is None:  # no valid target point: none within any distance
        out[rows, 1] = float(radius)
        return out
    count = min(2 if pairs else 1, kept.size)
    # Both libraries test `d < bound`: widen the bound by rounding (the allowance caps at 2r).
    bound = (reach if pairs else float(radius)) * (1 + 8 * np.finfo(queries.dtype).eps)
    every = rows.size == m  # (no gather or scatter of the rows: the usual case early on)
    d, i = tree_query(
        tree, np.ascontiguousarray(queries if every else queries[rows], dtype), count,
        distance_upper_bound=bound,
    )  # fmt: skip
    d = np.asarray(d, np.float64).reshape(rows.size, count)
    i = np.asarray(i).reshape(rows.size, count)
    first = d[:, 0]
    found = first < np.inf
    if count == 2 or kept.size == 1:  # (one valid target point: no other within any distance)
        second = np.minimum(d[:, 1], reach) if count == 2 else reach
        allowance = np.where(found, 0.5 * (second - first), float(radius) if pairs else 0.0)
    else:  # the nearest point within r only: no allowance for a match, nor for none
        allowance = np.zeros_like(first)
    # (a miss reports the index len(kept) in both libraries: clipped, then masked)
    slot = np.where(found, kept[np.minimum(i[:, 0], kept.size - 1)], -1)
    destination = slice(None) if every else rows
    out[destination, 0] = slot
    out[destination, 1] = allowance
    return out
