r"""Surface normals by principal component analysis over nearest neighbours.

The normal at $p$ is the eigenvector of the smallest eigenvalue of the covariance of its
neighbourhood (the point and its `k - 1` nearest neighbours, optionally only those within
`radius`: Open3D's `KDTreeSearchParamHybrid(radius, max_nn=k)`), computed in closed form
(Smith, "Eigenvalues of a symmetric 3x3 matrix", CACM 1961, then the largest cross product of
two rows of $A - \lambda I$), and flipped to face `viewpoint`.

The neighbourhoods (`neighbourhoods`) come from a k-d tree on a CPU (exact, and no search to
compile; under `jit` and `vmap` too): the native library's (`lieax.icp._native_kdtree.neighbours`,
one custom call that builds and queries it), else, without that library, one on the host through
`host_call` (`lieax.icp._host_kdtree.nearest_valid_rows`, pykdtree's tree where it is installed,
else SciPy's `cKDTree` built so that it survives XLA's callbacks, see `_host_kdtree.host_tree`,
and a program that JAX's persistent compilation cache cannot keep). Elsewhere
they come from the fixed-shape neighbour graph of `lieax.icp._neighbors` (the graph's build
compiles for seconds; 99.96% of the bunny's neighbourhoods exact). The covariances and
eigenvectors are computed in JAX from those neighbourhoods (`normals_from_neighbourhoods`), so
that `lieax.icp._implicit` can differentiate them with the neighbourhoods held fixed.
"""

import functools

import jax
import jax.numpy as jnp

from .. import _cpu_emitters as cpu_emitters
from .._host_call import host_call
from . import _host_kdtree, _native_kdtree, _neighbors, _search
from ._checks import check_cloud, check_count, check_mask

NORMAL_SEARCHES = ("auto", "kdtree", "graph")
_UPPER = ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))


def estimate_normals(
    points, *, k=30, radius=None, mask=None, viewpoint=(0.0, 0.0, 0.0), search="auto"
):
    r"""Unit normals of a point cloud, shape `(n, 3)`.

    **Arguments:**

    - `points`: shape `(n, 3)`.
    - `k`: neighbourhood size, the point itself included.
    - `radius`: if given, only neighbours within this distance count.
    - `mask`: `(n,)` bools, False for padding; those rows get `(0, 0, 0)`.
    - `viewpoint`: each normal is flipped to point toward it ($n^\top (v - p) \ge 0$), e.g. the
      sensor position; `None` leaves the sign the eigen solver gives.
    - `search`: how the neighbourhoods are found: `"kdtree"` (a k-d tree, the native library's,
      else pykdtree's or SciPy's on the host; exact; CPU only), `"graph"` (the fixed-shape neighbour graph,
      any backend) or `"auto"` (`"kdtree"` on a CPU, else `"graph"`).

    Neighbourhoods with fewer than 3 points give `(0, 0, 1)`. Runs under `jit` and `vmap`.
    """
    points = check_cloud(points, "points")
    mask = check_mask(mask, points, "mask")
    k = check_count(k, "k", minimum=3)
    found = neighbourhoods(points, mask, k, search=search)
    return normals_from_neighbourhoods(points, mask, found, radius=radius, viewpoint=viewpoint)


def neighbourhoods(points, mask, k, *, search="auto"):
    """The `k` nearest valid points of every valid point of `points` `(n, 3)` (itself among them),
    `(n, k)` int32 indices, `-1` where there are fewer and in the rows of invalid points (`mask`
    False, or not finite). `search` as `estimate_normals`'s."""
    if search not in NORMAL_SEARCHES:
        raise ValueError(f"search must be one of {NORMAL_SEARCHES}, got {search!r}.")
    if search == "auto":
        search = "kdtree" if _search.platform_of(points) == "cpu" else "graph"
    if search == "kdtree":
        _host_kdtree.check_on_host(points, "the points")
        library = _host_kdtree.default_library(points.dtype)
        # (the neighbourhoods are piecewise constant in the points: no derivative to carry)
        fixed = jax.lax.stop_gradient(points)
        return _kdtree_neighbourhoods_call(fixed, mask, k=k, library=library)
    return _graph_neighbourhoods(points, mask, k=k)


@functools.partial(jax.jit, static_argnames=("k", "library"))
def _kdtree_neighbourhoods_call(points, mask, *, k, library):
    valid = mask & jnp.all(jnp.isfinite(points), axis=1)
    if library == "native":
        return _native_kdtree.neighbours(points, valid, k)
    result = jax.ShapeDtypeStruct((points.shape[0], k), jnp.int32)
    host = functools.partial(_host_kdtree.nearest_valid_rows, k=k, library=library)
    return host_call(host, result, points, valid)


@cpu_emitters.jit(static_argnames=("k",))
def _graph_neighbourhoods(points, mask, *, k):
    """The point and its `k - 1` neighbours in the graph of `_neighbors.build_index`, in the
    cloud's own order."""
    safe = jnp.where(mask[:, None] & jnp.isfinite(points), points, 0.0)
    index = _neighbors.build_index(safe, mask, degree=k - 1, adjacent_leaves=16 if k <= 16 else 24)
    slots = jnp.arange(index.points.shape[0], dtype=jnp.int32)
    members = jnp.concatenate([slots[:, None], index.graph], axis=1)  # (slots, k), itself first
    rows = jnp.where(index.valid[members], index.order[members], -1)
    destination = jnp.where(index.valid, index.order, points.shape[0])
    empty = jnp.full((points.shape[0], k), -1, jnp.int32)
    return empty.at[destination].set(rows, mode="drop")


def normals_from_neighbourhoods(points, mask, found, *, radius=None, viewpoint=(0.0, 0.0, 0.0)):
    """`estimate_normals` of `points` over the neighbourhoods `found` (from `neighbourhoods`)."""
    view = None if viewpoint is None else jnp.asarray(viewpoint, points.dtype)
    radius = jnp.asarray(jnp.inf if radius is None else radius, points.dtype)
    return _normals(points, mask, found, radius, view)


@cpu_emitters.jit
def _normals(points, mask, found, radius, viewpoint):
    valid = mask & jnp.all(jnp.isfinite(points), axis=1)
    safe = jnp.where(valid[:, None], points, 0.0)
    covariance, count = neighbourhood_covariances(safe, found, radius)
    normals = smallest_eigenvector(covariance)
    normals = jnp.where((count >= 3)[:, None], normals, jnp.array([0.0, 0.0, 1.0], points.dtype))
    if viewpoint is not None:
        facing = jnp.sum(normals * (viewpoint - safe), axis=1)
        normals = jnp.where((facing < 0)[:, None], -normals, normals)
    return jnp.where(valid[:, None], normals, 0.0)


def neighbourhood_covariances(points, found, radius=jnp.inf):
    r"""The covariance $\frac1c \sum_j (p_j - \bar p)(p_j - \bar p)^\top$ of each neighbourhood
    (`found` `(n, k)`, `-1` for none; only members within `radius` of the point), `(n, 3, 3)`,
    and the count $c$ of its members, `(n,)`. The six products are written out (batched 3x3
    products run slowly on the CPU)."""
    inside = found >= 0
    members = jnp.transpose(points[jnp.maximum(found, 0)], (0, 2, 1))  # (n, 3, k)
    offsets = members - points[:, :, None]
    inside = inside & (jnp.sum(offsets * offsets, axis=1) <= radius * radius)
    return offset_covariances(offsets, inside)


def offset_covariances(offsets, inside):
    r"""The sample covariance of the offsets `(n, 3, k)` where `inside` `(n, k)`, `(n, 3, 3)`, and
    the count of those, `(n,)`. The six products are written out (batched 3x3 products run
    slowly on the CPU)."""
    count = jnp.sum(inside, axis=1)
    offsets = jnp.where(inside[:, None, :], offsets, 0.0)
    mean = jnp.sum(offsets, axis=2) / jnp.maximum(count, 1)[:, None]
    centred = jnp.where(inside[:, None, :], offsets - mean[:, :, None], 0.0)
    rows = [centred[:, a, :] for a in range(3)]
    products = {(a, b): jnp.sum(rows[a] * rows[b], axis=1) for a, b in _UPPER}
    entries = [[products[min(a, b), max(a, b)] for b in range(3)] for a in range(3)]
    covariance = jnp.stack([jnp.stack(row, -1) for row in entries], -2)
    return covariance / jnp.maximum(count, 1)[:, None, None], count


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
