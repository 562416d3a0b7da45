r"""Surface normals by principal component analysis over nearest neighbours.

The normal at $p$ is the eigenvector of the smallest eigenvalue of the covariance of its
neighbourhood (the point and its `k - 1` nearest neighbours, optionally only those within
`radius`: Open3D's `KDTreeSearchParamHybrid(radius, max_nn=k)`), computed in closed form
(Smith, "Eigenvalues of a symmetric 3x3 matrix", CACM 1961, then the largest cross product of
two rows of $A - \lambda I$), and flipped to face `viewpoint`.
"""

import functools

import jax
import jax.numpy as jnp

from . import _neighbors
from ._checks import check_cloud, check_count, check_mask


def estimate_normals(points, *, k=30, radius=None, mask=None, viewpoint=(0.0, 0.0, 0.0)):
    r"""Unit normals of a point cloud, shape `(n, 3)`.

    **Arguments:**
    - `points`: shape `(n, 3)`.
    - `k`: neighbourhood size, the point itself included.
    - `radius`: if given, only neighbours within this distance count.
    - `mask`: `(n,)` bools, False for padding; those rows get `(0, 0, 0)`.
    - `viewpoint`: each normal is flipped to point toward it ($n^\top (v - p) \ge 0$), e.g. the
      sensor position; `None` leaves the sign the eigen solver gives.

    Neighbourhoods with fewer than 3 points give `(0, 0, 1)`. Runs under `jit` and `vmap`.
    """
    points = check_cloud(points, "points")
    mask = check_mask(mask, points, "mask")
    k = check_count(k, "k", minimum=3)
    view = None if viewpoint is None else jnp.asarray(viewpoint, points.dtype)
    return _estimate(
        points, mask, jnp.asarray(jnp.inf if radius is None else radius, points.dtype), view, k=k
    )


@functools.partial(jax.jit, static_argnames=("k",))
def _estimate(points, mask, radius, viewpoint, *, k):
    safe = jnp.where(mask[:, None] & jnp.isfinite(points), points, 0.0)
    index = _neighbors.build_index(
        safe, mask, degree=k - 1, links=0, adjacent_leaves=16 if k <= 16 else 24
    )
    centre = index.points  # slot order
    neighbours = jnp.concatenate(
        [centre[:, :, None], index.graph_points], axis=2
    )  # (slots, 3, k), the point first
    offsets = neighbours - centre[:, :, None]
    distance2 = jnp.sum(offsets * offsets, axis=1)
    member_valid = jnp.concatenate([index.valid[:, None], index.valid[index.graph]], axis=1)
    inside = member_valid & (distance2 <= radius * radius)
    count = jnp.sum(inside, axis=1)
    offsets = jnp.where(inside[:, None, :], offsets, 0.0)
    mean = jnp.sum(offsets, axis=2) / jnp.maximum(count, 1)[:, None]
    centred = jnp.where(inside[:, None, :], offsets - mean[:, :, None], 0.0)
    covariance = jnp.einsum("sik,sjk->sij", centred, centred) / jnp.maximum(count, 1)[:, None, None]
    normals = smallest_eigenvector(covariance)
    normals = jnp.where((count >= 3)[:, None], normals, jnp.array([0.0, 0.0, 1.0], points.dtype))
    if viewpoint is not None:
        facing = jnp.sum(normals * (viewpoint - centre), axis=1)
        normals = jnp.where((facing < 0)[:, None], -normals, normals)
    normals = jnp.where(index.valid[:, None], normals, 0.0)
    slots = jnp.where(index.valid, index.order, points.shape[0])
    return jnp.zeros_like(points).at[slots].set(normals, mode="drop")


def smallest_eigenvector(matrix):
    """Unit eigenvector of the smallest eigenvalue of symmetric 3x3 matrices `(..., 3, 3)`."""
    scale = jnp.max(jnp.abs(matrix), axis=(-2, -1), keepdims=True)
    a = matrix / jnp.where(scale > 0, scale, 1.0)
    a00, a11, a22 = a[..., 0, 0], a[..., 1, 1], a[..., 2, 2]
    a01, a02, a12 = a[..., 0, 1], a[..., 0, 2], a[..., 1, 2]
    q = (a00 + a11 + a22) / 3.0
    p1 = a01 * a01 + a02 * a02 + a12 * a12
    p2 = (a00 - q) ** 2 + (a11 - q) ** 2 + (a22 - q) ** 2 + 2.0 * p1
    p = jnp.sqrt(p2 / 6.0)
    safe_p = jnp.where(p > 0, p, 1.0)
    b = (a - q[..., None, None] * jnp.eye(3, dtype=a.dtype)) / safe_p[..., None, None]
    half_det = 0.5 * jnp.linalg.det(b)
    phi = jnp.arccos(jnp.clip(half_det, -1.0, 1.0)) / 3.0
    smallest = q + 2.0 * p * jnp.cos(phi + 2.0 * jnp.pi / 3.0)
    shifted = a - smallest[..., None, None] * jnp.eye(3, dtype=a.dtype)
    r0, r1, r2 = shifted[..., 0, :], shifted[..., 1, :], shifted[..., 2, :]
    candidates = jnp.stack([jnp.cross(r0, r1), jnp.cross(r0, r2), jnp.cross(r1, r2)], axis=-2)
    norms = jnp.sum(candidates * candidates, axis=-1)
    best = jnp.argmax(norms, axis=-1)
    vector = jnp.take_along_axis(candidates, best[..., None, None], axis=-2)[..., 0, :]
    length = jnp.sqrt(jnp.take_along_axis(norms, best[..., None], axis=-1))
    fallback = jnp.array([0.0, 0.0, 1.0], dtype=a.dtype)
    return jnp.where(length > 0, vector / jnp.where(length > 0, length, 1.0), fallback)
