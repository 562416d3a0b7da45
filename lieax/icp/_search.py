"""Nearest-neighbour search backends, one interface: `build_index(..., search=...)`, `nearest`.

- `"grid"`: `GridIndex`, a voxel hash grid with cells of the radius (`_grid`); the 27 cells
  around a query, each scanned in full. Cheap to build, inside JAX (accelerators).
- `"kdtree"`: `KDTreeIndex`, a k-d tree in the native library (`_native_kdtree`, one custom call
  per build and per query batch), else pykdtree's or SciPy's on the host (`_host_kdtree`, one
  host call per query batch). Cheapest to build on a CPU.
- `"brute"`: `BruteIndex`, every target point against every query, chunk by chunk.

All answer exactly (the nearest valid target point within the radius, up to ties, or none) in
every call.

`"auto"` picks `"kdtree"` on a CPU: in ICP (`benchmarks/icp.py`, "Every kind of scan") it is the
fastest backend on the object scans, the LiDAR scans and the Kinect frame alike, and `"grid"` is
2-9x slower on a CPU. (A warm-started descent on a k-nearest-neighbour graph, `search="graph"`,
was removed: per registration it was 4.5-12.5x slower than the k-d tree on the four scans of
`benchmarks/icp.py`, its build alone 0.03-6 s, and with its index prebuilt and reused 2-6x
slower on three of them and 9% faster on the full bunny; see the changelog.) Elsewhere it picks `"brute"` for targets of at most `BRUTE_MAX_TARGET` points and
`"grid"` above (`"brute"` when no radius is given): a rule not yet measured on an accelerator.
"""

import math
from typing import NamedTuple

import jax
import jax.numpy as jnp

from . import _grid, _host_kdtree
from ._checks import check_parameter
from ._coordinates import squared_norms

SEARCHES = ("auto", "grid", "kdtree", "brute")
BRUTE_MAX_TARGET = 16384
_BRUTE_BLOCK = 2**21  # query chunk x target elements per step of the brute-force search


class Neighbors(NamedTuple):
    """The nearest target point of each query (`nearest`).

    **Fields:**

    - `index`: `(n,)` int32, index of the nearest point in the original target cloud, `-1` for
      none within the radius.
    - `slot`: `(n,)` int32, the same point's slot in the index (for warm starts).
    - `distance`: `(n,)` Euclidean distance to it (`inf` where there is none).
    - `certified`: `(n,)` bool, the match is exact within the search radius (every query that
      was searched: all backends are exact).
    """

    index: jax.Array
    slot: jax.Array
    distance: jax.Array
    certified: jax.Array


class BruteIndex(NamedTuple):
    """A target cloud for brute-force search. **Fields:** `points` `(N, 3)` (invalid rows hold
    `inf`), `order` `(N,)` int32 `arange(N)`, `valid` `(N,)` bool."""

    points: jax.Array
    order: jax.Array
    valid: jax.Array


def check_search(search) -> str:
    if search not in SEARCHES:
        raise ValueError(f"search must be one of {SEARCHES}, got {search!r}.")
    return search


def resolve(search, target_size, has_radius=True, platform=None) -> str:
    """The backend `"auto"` stands for (see the module docstring); other names pass through."""
    check_search(search)
    if search != "auto":
        return search
    platform = jax.default_backend() if platform is None else platform
    if platform == "cpu":
        return "kdtree"
    return "grid" if has_radius and target_size > BRUTE_MAX_TARGET else "brute"


def build_index(points, mask=None, *, search="auto", max_distance=None, **options):
    """Prepare a target cloud `points` (shape `(n, 3)`) for nearest-neighbour queries; runs under
    `jit` and `vmap`.

    **Arguments:**

    - `points`, `mask`: the target cloud; rows where `mask` is False are ignored (padding).
    - `search`: the backend (see the module docstring).
    - `max_distance`: the largest query radius; needed by `"grid"` (its cell size).
    - `options`: passed on to the backend's builder (`library` for `"kdtree"`; `capacity` for
      `"grid"`).

    **Returns:** a `GridIndex`, `KDTreeIndex` or `BruteIndex`.
    """
    points = jnp.asarray(points)
    if points.ndim != 2 or points.shape[-1] != 3:
        raise ValueError(f"points must have shape (n, 3), got shape {tuple(points.shape)}.")
    search = resolve(search, points.shape[0], max_distance is not None, platform_of(points))
    if search == "grid":
        if max_distance is None:
            raise ValueError("search='grid' needs max_distance (the cell size of the grid).")
        check_parameter(max_distance, "max_distance", positive=True)
        return _grid.build_grid(points, mask, cell_size=max_distance, **options)
    if search == "kdtree":
        return _host_kdtree.build_kdtree(points, mask, **options)
    if options:
        raise TypeError(f"search='brute' takes no options, got {sorted(options)}.")
    n = points.shape[0]
    valid = jnp.ones((n,), bool) if mask is None else jnp.asarray(mask, bool)
    valid = valid & jnp.all(jnp.isfinite(points), axis=1)
    points = jnp.where(valid[:, None], points, jnp.inf)
    return BruteIndex(points, jnp.arange(n, dtype=jnp.int32), valid)


def platform_of(points):
    """The platform (`"cpu"`, `"gpu"`, ...) of `points` (the default one while tracing)."""
    if isinstance(points, jax.core.Tracer) or not isinstance(points, jax.Array):
        return jax.default_backend()
    return next(iter(points.devices())).platform


def search_name(index) -> str:
    """The backend of an index."""
    for name, kind in (
        ("grid", _grid.GridIndex),
        ("kdtree", _host_kdtree.KDTreeIndex),
        ("brute", BruteIndex),
    ):
        if isinstance(index, kind):
            return name
    raise TypeError(f"not a neighbour index: {type(index).__name__} (see build_index).")


def match(index, queries, radius, mask=None, previous=None):
    """Exact matches from an index: the nearest valid target point within `radius` (inclusive) of each query, or none. `previous`: slots of earlier
    matches, a warm start for `"kdtree"` (see `lieax.icp._host_kdtree`).

    The search sees the queries through `stop_gradient`; the squared distance is then recomputed
    from the match, so its derivative with respect to the queries, $2(q - p)$, is exact in forward
    and reverse mode (the match itself is piecewise constant).

    **Returns:** `(slot, squared_distance)`, slot 0 and `inf` where there is none.
    """
    name = search_name(index)
    fixed = jax.lax.stop_gradient(queries)
    if name == "grid":
        slot, d2 = _grid.nearest_in_grid(index, fixed, radius, mask=mask)
    elif name == "kdtree":
        slot, d2 = _host_kdtree.nearest_in_kdtree(
            index, fixed, radius, mask=mask, previous=previous
        )
    else:
        slot, d2 = _brute_force(index, fixed, radius, mask)
    found = d2 < jnp.inf
    gap = jnp.where(found[:, None], queries - index.points[slot].astype(queries.dtype), 0.0)
    return slot, jnp.where(found, squared_norms(gap), jnp.inf)


def _brute_force(index: BruteIndex, queries, radius, mask):
    """Every target point against every query, `lax.map` over chunks of queries sized so that a
    chunk's distance matrix has about `_BRUTE_BLOCK` entries."""
    m, n = queries.shape[0], index.points.shape[0]
    active = jnp.ones((m,), bool) if mask is None else jnp.asarray(mask, bool)
    active = active & jnp.all(jnp.isfinite(queries), axis=1)
    chunk = max(1, min(m, _BRUTE_BLOCK // max(n, 1)))
    chunks = math.ceil(m / chunk)
    padding = jnp.zeros((chunks * chunk - m, 3), queries.dtype)
    padded = jnp.concatenate([jnp.where(active[:, None], queries, 0.0), padding])
    padded = padded.reshape(chunks, chunk, 3)
    targets = index.points.astype(queries.dtype)

    def one_chunk(q):
        d2 = sum((q[:, None, axis] - targets[None, :, axis]) ** 2 for axis in range(3))
        return _min_and_argmin(jnp.where(jnp.isnan(d2), jnp.inf, d2))

    d2, slot = jax.lax.map(one_chunk, padded)
    d2, slot = d2.reshape(-1)[:m], slot.reshape(-1)[:m]
    r2 = jnp.asarray(radius, queries.dtype) ** 2
    found = active & (d2 <= r2)
    return jnp.where(found, slot, 0), jnp.where(found, d2, jnp.inf)


def _min_and_argmin(d2):
    """Row minima and the first column attaining them (two plain reductions: XLA's variadic
    argmin reduction is much slower on the CPU)."""
    d2 = jax.lax.optimization_barrier(d2)
    smallest = jnp.min(d2, axis=-1)
    columns = d2.shape[-1]
    first = jnp.min(
        jnp.where(d2 == smallest[..., None], jnp.arange(columns, dtype=jnp.int32), columns), axis=-1
    )
    return smallest, jnp.minimum(first, columns - 1)


def nearest(index, queries, *, radius=jnp.inf, initial=None, mask=None) -> Neighbors:
    """The nearest target point of every query, exact within `radius`.

    **Arguments:**

    - `index`: from `build_index` (any backend).
    - `queries`: shape `(n, 3)`.
    - `radius`: the search radius. `"grid"` searches within its cell size at most; every
      backend reports no match (`index = -1`, `distance = inf`) beyond `radius`.
    - `initial`: slots of earlier matches (a previous `Neighbors.slot`), a warm start for
      `"kdtree"`.
    - `mask`: queries to skip (their result is meaningless).

    **Returns:** `Neighbors`.
    """
    queries = jnp.asarray(queries)
    if queries.ndim != 2 or queries.shape[-1] != 3:
        raise ValueError(f"queries must have shape (n, 3), got shape {tuple(queries.shape)}.")
    active = jnp.ones(queries.shape[:1], bool) if mask is None else jnp.asarray(mask, bool)
    slot, d2 = match(index, queries, radius, active, previous=initial)
    found = d2 < jnp.inf
    return Neighbors(jnp.where(found, index.order[slot], -1), slot, jnp.sqrt(d2), active)


def check_icp_search(search, target, max_distance):
    """ICP's `search=`: a backend name (`"auto"` resolved for `target`) or a prebuilt index of
    `target`. **Returns:** `(name, index or None)`."""
    if isinstance(search, str):
        check_search(search)
        return resolve(search, target.shape[0], True, platform_of(target)), None
    name = search_name(search)
    if search.points.shape[-2:] != target.shape:
        raise ValueError(
            f"the prebuilt index holds {search.points.shape[-2]} points, the target "
            f"{target.shape[0]}: build it on this target."
        )
    if name == "grid":
        concrete = not any(isinstance(x, jax.core.Tracer) for x in (search.cell_size, max_distance))
        if concrete and float(search.cell_size) < float(max_distance):
            raise ValueError(
                f"the prebuilt grid's cell size {float(search.cell_size):g} is below "
                f"max_correspondence_distance={float(max_distance):g}: matches would not be exact."
            )
    return name, search
