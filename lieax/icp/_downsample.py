"""Voxel-grid downsampling: the centroid of the points in each occupied voxel (Open3D's
`voxel_down_sample`: voxels of side `voxel_size` anchored at the cloud's minimum minus half a
voxel)."""

from typing import overload

import jax
import jax.numpy as jnp
import numpy as np
from jax.typing import ArrayLike

from ._checks import check_cloud, check_count, check_mask, check_parameter


@overload
def voxel_downsample(
    points: ArrayLike, voxel_size: ArrayLike, *, mask: ArrayLike | None = None, size: None = None
) -> jax.Array: ...
@overload
def voxel_downsample(
    points: ArrayLike,
    voxel_size: ArrayLike,
    *,
    mask: ArrayLike | None = None,
    size: int | np.integer,
) -> tuple[jax.Array, jax.Array]: ...
def voxel_downsample(points, voxel_size, *, mask=None, size=None):
    """Replace the points in each voxel of side `voxel_size` by their centroid.

    **Arguments:**

    - `points`: shape `(n, 3)`.
    - `voxel_size`: side of the voxels (positive).
    - `mask`: `(n,)` bools, False for points to ignore (padding).
    - `size`: `None` for an exact-size result (eager use: the number of voxels decides the
      shape); an int for a fixed-shape result under `jit` / `vmap`: the first `size` voxels.

    **Returns:** with `size=None`, the centroids `(m, 3)`, ordered by voxel (x, then y, then z);
    otherwise `(centroids (size, 3), mask (size,))`, rows past the number of voxels zero and
    masked out.
    """
    points = check_cloud(points, "points")
    mask = check_mask(mask, points, "mask")
    check_parameter(voxel_size, "voxel_size", positive=True)
    voxel_size = jnp.asarray(voxel_size, points.dtype)
    centroids, count = _downsample(points, mask, voxel_size)
    if size is None:
        return centroids[: int(count)]
    size = check_count(size, "size", minimum=1)
    if size > points.shape[0]:
        centroids = jnp.concatenate(
            [centroids, jnp.zeros((size - points.shape[0], 3), centroids.dtype)]
        )
    return centroids[:size], jnp.arange(size) < count


@jax.jit
def _downsample(points, mask, voxel_size):
    n = points.shape[0]
    valid = mask & jnp.all(jnp.isfinite(points), axis=1)
    lowest = jnp.min(jnp.where(valid[:, None], points, jnp.inf), axis=0) - 0.5 * voxel_size
    cell = jnp.floor((points - lowest) / voxel_size)
    cell = jnp.where(valid[:, None], cell, -1).astype(jnp.int32)  # invalid points sort first
    order = jnp.lexsort((cell[:, 2], cell[:, 1], cell[:, 0]))
    cell, ordered, ordered_valid = cell[order], points[order], valid[order]
    starts = jnp.concatenate([jnp.ones((1,), bool), jnp.any(cell[1:] != cell[:-1], axis=1)])
    starts = starts & ordered_valid
    group = jnp.cumsum(starts) - 1  # invalid points (first) get group -1
    group = jnp.where(ordered_valid, group, n)
    sums = jax.ops.segment_sum(jnp.where(ordered_valid[:, None], ordered, 0.0), group, n + 1)[:n]
    counts = jax.ops.segment_sum(ordered_valid.astype(points.dtype), group, n + 1)[:n]
    centroids = jnp.where(counts[:, None] > 0, sums / jnp.maximum(counts, 1)[:, None], 0.0)
    return centroids, jnp.sum(starts)
