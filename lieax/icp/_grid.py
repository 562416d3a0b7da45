r"""A voxel hash grid of the target, built and queried under `jit` and `vmap` with fixed shapes.

The structure KISS-ICP and small_gicp use for their correspondences: cells of side `cell_size`
(the correspondence distance $r$, so that every target point within $r$ of a query lies in the
$3^3$ cells around the query's own), each cell's integer coordinates $(i, j, k)$ hashed into a
table of `capacity` (a power of two) buckets,
$h = (73856093\,i \oplus 19349663\,j \oplus 83492791\,k) \bmod$ `capacity` (Teschner et al.,
"Optimized spatial hashing for collision detection of deformable objects", VMV 2003). The target
points are sorted by bucket (one 32-bit integer sort of keys that pack the bucket with the point's
index, where both fit), and `start`/`count` give each bucket's run of points.

A query visits the 27 cells nearest first (its own, then faces, edges, corners), skipping a cell
whose box is farther than the best match so far (or than $r$), and scans each visited cell's bucket
`chunk` points per step until the bucket's count: a dense cell is scanned in full, never truncated,
so the match is the exact nearest target point within $r$ (up to ties), or none. Colliding cells
only add candidates (a bucket may hold points of other cells; the distance test discards them).
"""

import math
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from ._coordinates import squared_norms

_PRIMES = (73856093, 19349663, 83492791)
_COORD_LIMIT = 2.0**30  # cell coordinates are clipped to +-2**30 (int32, exact in float32)
# The 27 neighbouring cells, nearest first: the own cell, 6 faces, 12 edges, 8 corners.
_OFFSETS = np.array(
    sorted(
        ((i, j, k) for i in (-1, 0, 1) for j in (-1, 0, 1) for k in (-1, 0, 1)),
        key=lambda o: (abs(o[0]) + abs(o[1]) + abs(o[2]), o),
    ),
    np.int32,
)


class GridIndex(NamedTuple):
    """A target cloud in a voxel hash grid (see the module docstring). Shapes: `N` points,
    `M = capacity` buckets.

    **Fields:**

    - `points`: `(N, 3)` the target points sorted by bucket; invalid points hold `inf`.
    - `order`: `(N,)` int32, the index in the original cloud of each slot.
    - `valid`: `(N,)` bool.
    - `start`, `count`: `(M,)` int32, each bucket's first slot and number of valid points.
    - `origin`: `(3,)` the corner of cell `(0, 0, 0)`.
    - `cell_size`: `()` the side of a cell: queries are exact within it.
    """

    points: jax.Array
    order: jax.Array
    valid: jax.Array
    start: jax.Array
    count: jax.Array
    origin: jax.Array
    cell_size: jax.Array

    @property
    def capacity(self) -> int:
        return self.count.shape[-1]


def _cell_coordinates(points, origin, cell_size):
    scaled = jnp.floor((points - origin) / cell_size)
    scaled = jnp.where(jnp.isfinite(scaled), scaled, 0.0)
    return jnp.clip(scaled, -_COORD_LIMIT, _COORD_LIMIT).astype(jnp.int32)


def _bucket(cells, capacity):
    """The hash of integer cell coordinates `(..., 3)` int32, in `[0, capacity)`."""
    u = cells.astype(jnp.uint32)
    h = (u[..., 0] * jnp.uint32(_PRIMES[0])) ^ (u[..., 1] * jnp.uint32(_PRIMES[1]))
    h = h ^ (u[..., 2] * jnp.uint32(_PRIMES[2]))
    return (h & jnp.uint32(capacity - 1)).astype(jnp.int32)


def build_grid(points, mask=None, *, cell_size, capacity=None) -> GridIndex:
    """Hash `points` (shape `(n, 3)`) into a voxel grid of cells of side `cell_size`; runs under
    `jit` and `vmap` (`cell_size` may be traced).

    **Arguments:**

    - `points`: the target cloud. Rows where `mask` is False are ignored (padding).
    - `cell_size`: the side of a cell, positive: `nearest_in_grid` is exact within it.
    - `capacity`: buckets of the hash table, a power of two; default the power of two at or
      above `n` (at most one bucket per point on average; collisions cost time, not exactness).

    **Returns:** a `GridIndex`.
    """
    points = jnp.asarray(points)
    n = points.shape[0]
    if capacity is None:
        capacity = 2 ** max(4, math.ceil(math.log2(max(n, 1))))
    if capacity <= 0 or capacity & (capacity - 1):
        raise ValueError(f"capacity must be a power of two, got {capacity}.")
    valid = jnp.ones((n,), bool) if mask is None else jnp.asarray(mask, bool)
    valid = valid & jnp.all(jnp.isfinite(points), axis=1)
    cell_size = jnp.asarray(cell_size, points.dtype)
    origin = jnp.min(jnp.where(valid[:, None], points, jnp.inf), axis=0)
    origin = jnp.where(jnp.isfinite(origin), origin, 0.0)
    bucket = _bucket(_cell_coordinates(points, origin, cell_size), capacity)
    bucket = jnp.where(valid, bucket, capacity)  # invalid points sort last, in no bucket
    index_bits = max(1, math.ceil(math.log2(max(n, 2))))
    bucket_bits = math.ceil(math.log2(capacity + 1))
    iota = jnp.arange(n, dtype=jnp.int32)
    if index_bits + bucket_bits <= 32:  # one integer sort (XLA's key-value sort is slower)
        key = jnp.sort((bucket.astype(jnp.uint32) << index_bits) | iota.astype(jnp.uint32))
        order = (key & jnp.uint32(2**index_bits - 1)).astype(jnp.int32)
    else:
        _, order = jax.lax.sort((bucket, iota), num_keys=1)
    count = jnp.zeros((capacity + 1,), jnp.int32).at[bucket].add(1)[:capacity]
    start = (jnp.cumsum(count) - count).astype(jnp.int32)
    valid = valid[order]
    sorted_points = jnp.where(valid[:, None], points[order], jnp.inf)
    return GridIndex(sorted_points, order, valid, start, count, origin, cell_size)


def nearest_in_grid(index: GridIndex, queries, radius=None, *, mask=None, chunk=8):
    """The nearest target point within `radius` of each query (exact up to ties), or none.

    **Arguments:**

    - `index`: from `build_grid`.
    - `queries`: shape `(n, 3)`.
    - `radius`: the search radius, at most `index.cell_size` (the default); a larger one is
      clipped to it.
    - `mask`: queries to skip (they get no match).
    - `chunk`: points of one bucket scanned per query and step.

    **Returns:** `(slot, squared_distance)`: the match's slot in `index` (0 where there is none)
    and its squared distance (`inf` where there is none).
    """
    queries = jnp.asarray(queries)
    m = queries.shape[0]
    active = jnp.ones((m,), bool) if mask is None else jnp.asarray(mask, bool)
    active = active & jnp.all(jnp.isfinite(queries), axis=1)
    cell_size = index.cell_size.astype(queries.dtype)
    r = cell_size if radius is None else jnp.minimum(jnp.asarray(radius, queries.dtype), cell_size)
    r2 = r * r
    queries = jnp.where(active[:, None], queries, 0.0)
    own = _cell_coordinates(queries, index.origin, cell_size)
    offsets = jnp.asarray(_OFFSETS)
    buckets = _bucket(own[:, None, :] + offsets, index.capacity)  # (m, 27)
    # Distance from the query to each neighbouring cell's box: per axis, to the shared face.
    # Rounding moves a query by up to a few ulps of its cell coordinate: shrink the gaps by that.
    scaled = (queries - index.origin) / cell_size
    inside = (scaled - own)[:, None, :]  # in [0, 1) within the own cell
    slack = 4 * jnp.finfo(queries.dtype).eps * (jnp.abs(scaled) + 1)[:, None, :]
    gap = jnp.where(offsets == -1, inside, jnp.where(offsets == 1, 1 - inside, 0.0))
    gap = jnp.maximum(gap - slack, 0.0) * cell_size
    box2 = squared_norms(gap)  # (m, 27)
    starts, counts = index.start[buckets], index.count[buckets]
    wanted = (box2 <= r2) & (counts > 0) & active[:, None]
    cells = jnp.arange(27, dtype=jnp.int32)
    lanes = jnp.arange(chunk, dtype=jnp.int32)

    def next_cell(after, best2):
        ok = wanted & (cells > after[:, None]) & (box2 < best2[:, None])
        return jnp.min(jnp.where(ok, cells, 27), axis=1)

    def step(state):
        cell, offset, slot, best2 = state
        live = cell < 27
        column = jnp.minimum(cell, 26)[:, None]
        first = jnp.take_along_axis(starts, column, axis=1)[:, 0]
        total = jnp.take_along_axis(counts, column, axis=1)[:, 0]
        position = offset[:, None] + lanes
        present = live[:, None] & (position < total[:, None])
        candidate = jnp.where(present, first[:, None] + position, 0)
        d2 = sum((index.points[candidate, axis] - queries[:, None, axis]) ** 2 for axis in range(3))
        d2 = jnp.where(present & ~jnp.isnan(d2), d2, jnp.inf)
        smallest = jnp.min(d2, axis=1)
        lane = jnp.min(jnp.where(d2 == smallest[:, None], lanes, chunk), axis=1)
        found = jnp.take_along_axis(candidate, jnp.minimum(lane, chunk - 1)[:, None], axis=1)[:, 0]
        better = (smallest < best2) & (smallest <= r2)
        slot, best2 = jnp.where(better, found, slot), jnp.where(better, smallest, best2)
        offset = offset + chunk
        finished = offset >= total
        cell = jnp.where(live & finished, next_cell(cell, best2), cell)
        return cell, jnp.where(finished, 0, offset), slot, best2

    def keep_going(state):
        return jnp.any(state[0] < 27)

    best2 = jnp.full((m,), jnp.inf, queries.dtype)
    start = (next_cell(jnp.full((m,), -1, jnp.int32), best2), jnp.zeros((m,), jnp.int32),
             jnp.zeros((m,), jnp.int32), best2)  # fmt: skip
    _, _, slot, best2 = jax.lax.while_loop(keep_going, step, start)
    return slot, best2
