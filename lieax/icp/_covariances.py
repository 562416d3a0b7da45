r"""The covariances of Generalized ICP: each point's local surface as a 3x3 covariance, the
sample covariance of its `k` nearest neighbours regularized to a plane (eigenvalues
$(\epsilon, 1, 1)$ in the eigenbasis of the sample covariance: Segal, Haehnel, Thrun,
"Generalized-ICP", RSS 2009, Sec. III-B; $\epsilon = 10^{-3}$ as fast_gicp and small_gicp),
found by the k-d tree on a CPU and the neighbour graph elsewhere."""

import functools

import jax
import jax.numpy as jnp
import numpy as np
from jax.typing import ArrayLike

from .. import _cpu_emitters as cpu_emitters
from .._checks import as_float_array, is_concrete, to_device
from .._host_call import host_call
from . import _host_kdtree, _native_kdtree, _neighbors, _normals, _search
from ._batch import pad_to_bucket
from ._checks import check_cloud, check_count, check_mask
from ._normals import _UPPER, offset_covariances, smallest_eigenvector, upper_entry

EPSILON = 1e-3  # the smallest regularized eigenvalue (GICP, fast_gicp, small_gicp)
MIN_NEIGHBOURS = 5  # fewer valid neighbours give the identity (small_gicp's rule)


def estimate_covariances(
    points: ArrayLike,
    *,
    k: int | np.integer = 20,
    mask: ArrayLike | None = None,
    search: str = "auto",
) -> jax.Array:
    r"""Regularized local covariances of a point cloud, shape `(n, 3, 3)`.

    The sample covariance of each point and its `k - 1` nearest neighbours, eigen-decomposed as
    $U \Lambda U^\top$ (eigenvalues ascending), is replaced by
    $C = U\,\mathrm{diag}(\varepsilon, 1, 1)\,U^\top = I - (1 - \varepsilon)\,n n^\top$
    with $\varepsilon = 10^{-3}$ and $n$ the eigenvector of the smallest eigenvalue: the "plane"
    regularization of Segal et al. (2009, section III.B), as small_gicp's `CovarianceSetter` and
    fast_gicp's `PLANE` method. Neighbourhoods of fewer than 5 valid points get the identity
    (small_gicp's rule).

    **Arguments:**

    - `points`: shape `(n, 3)`.
    - `k`: neighbourhood size, the point itself included (small_gicp's default, 20).
    - `mask`: `(n,)` bools, False for padding; those rows get the identity.
    - `search`: how the neighbours are found, as for `estimate_normals`: `"kdtree"`, a k-d tree
      (the native library's, else pykdtree's or SciPy's on the host; exact; CPU only; the sums
      over each neighbourhood are made beside it, see `_kdtree_covariances`), `"graph"`, the
      fixed-shape neighbour graph (any backend;
      99.96% of the bunny's neighbourhoods exact), or `"auto"` (`"kdtree"` on a CPU, else
      `"graph"`).

    Runs under `jit` and `vmap`.
    """
    points = check_cloud(points, "points")
    mask = check_mask(mask, points, "mask")
    k = check_count(k, "k", minimum=MIN_NEIGHBOURS)
    if search not in ("auto", "graph", "kdtree"):
        raise ValueError(f"search must be 'auto', 'graph' or 'kdtree', got {search!r}.")
    if search == "auto":
        search = "kdtree" if _search.platform_of(points) == "cpu" else "graph"
    if search == "kdtree":
        _host_kdtree.check_on_host(points, "the points")
        return _kdtree_covariances(points, mask, k, _host_kdtree.default_library(points.dtype))
    return _estimate(points, mask, k=k)


@cpu_emitters.jit(static_argnames=("k",))
def _estimate(points, mask, *, k):
    safe = jnp.where(mask[:, None] & jnp.isfinite(points), points, 0.0)
    # 16 adjacent leaves of 16 points: 99.96% of the bunny's 20-neighbourhoods are exact (24 leaves:
    # 99.97%, at twice the build time; the rest swap a far neighbour for an almost as near one).
    index = _neighbors.build_index(safe, mask, degree=k - 1, adjacent_leaves=16)
    centre = index.points  # slot order
    neighbours = jnp.concatenate([centre[:, :, None], index.graph_points], axis=2)  # (slots, 3, k)
    # Clouds of fewer valid points than k fill the graph with invalid slots, the point itself and
    # (fewer slots than k - 1) repeats: count each valid neighbour once.
    others = index.valid[index.graph] & (index.graph != jnp.arange(index.graph.shape[0])[:, None])
    if index.graph.shape[0] < k - 1:
        earlier = jnp.tril(jnp.ones((k - 1, k - 1), bool), -1)
        repeated = jnp.any((index.graph[:, :, None] == index.graph[:, None, :]) & earlier, axis=2)
        others = others & ~repeated
    inside = jnp.concatenate([index.valid[:, None], others], axis=1)
    regularized = _regularized(centre, neighbours, inside, index.valid)
    slots = jnp.where(index.valid, index.order, points.shape[0])
    identities = jnp.broadcast_to(jnp.eye(3, dtype=points.dtype), (points.shape[0], 3, 3))
    return identities.at[slots].set(regularized, mode="drop")


@cpu_emitters.jit
def _covariances_of_neighbours(points, mask, found):
    """The covariances over the neighbourhoods `found` (`-1` for none) of `_normals.neighbourhoods`
    (the host k-d tree's: exact)."""
    valid = mask & jnp.all(jnp.isfinite(points), axis=1)
    safe = jnp.where(valid[:, None], points, 0.0)
    neighbours = jnp.transpose(safe[jnp.maximum(found, 0)], (0, 2, 1))  # (n, 3, k)
    return _regularized(safe, neighbours, found >= 0, valid)


@functools.partial(jax.custom_jvp, nondiff_argnums=(2, 3))
def _kdtree_covariances(points, mask, k, library):
    """`estimate_covariances(search="kdtree")`: the neighbours' sums beside the k-d tree, in the
    native library's custom call (`lieax.icp._native_kdtree.covariance_entries`) or the host
    tree's callback (`_host_covariance_entries`), the eigenvector and the regularization in JAX.

    Either skips what the JAX path of `_covariances_of_neighbours` pays for: the `(n, k)`
    indices' trip back to XLA and XLA's gather of `(n, 3, k)` copies (on the Kinect cloud of
    `benchmarks/gicp.py`, 67k points, about 2x the time of the NumPy sums). Derivatives (the
    neighbourhoods held fixed) are those of `_covariances_of_neighbours`, the JVP rule below."""
    return _kdtree_covariances_primal(points, mask, k=k, library=library)


@cpu_emitters.jit(static_argnames=("k", "library"))
def _kdtree_covariances_primal(points, mask, *, k, library):
    valid = mask & jnp.all(jnp.isfinite(points), axis=1)
    if library == "native":
        entries = _native_kdtree.covariance_entries(points, valid, k)
    else:
        host = functools.partial(_host_covariance_entries, k=k, library=library)
        result = jax.ShapeDtypeStruct((points.shape[0], 6), points.dtype)
        entries = host_call(host, result, points, valid)
    upper = [entries[:, j] for j in range(6)]
    covariance = jnp.stack(
        [jnp.stack([upper_entry(upper, a, b) for b in range(3)], -1) for a in range(3)], -2
    )
    count = jnp.minimum(k, jnp.sum(valid))  # every valid point has min(k, valid points) members
    return _plane_regularized(covariance, count, valid)


@_kdtree_covariances.defjvp
def _kdtree_covariances_jvp(k, library, primals, tangents):
    points, mask = primals
    found = _normals.neighbourhoods(points, mask, k, search="kdtree")
    return jax.jvp(lambda p: _covariances_of_neighbours(p, mask, found), (points,), tangents[:1])


def _host_covariance_entries(points, valid, k, library):
    r"""Host side of `_kdtree_covariances`: the six upper entries `(00, 01, 02, 11, 12, 22)` of
    the sample covariance of each valid row of `points` `(n, 3)` and its `k - 1` nearest valid
    rows (fewer where there are fewer), `(n, 6)` in the points' dtype, 0 in the rows not `valid`.

    The neighbourhoods are `_host_kdtree.valid_row_neighbours`'; then, in float64 with the
    offsets $o_j = p_j - p$ from the point, $\frac1c \sum_j o_j o_j^\top - \bar o \bar o^\top$
    (small_gicp's sums, about the point rather than the origin), one coordinate at a time: three
    `(n, k)` gathers, no `(n, k, 3)` copy."""
    out = np.zeros((points.shape[0], 6), points.dtype)
    rows, cloud, nearest = _host_kdtree.valid_row_neighbours(points, valid, k, library)
    if nearest is None:
        return out
    count = nearest.shape[1]
    columns = np.ascontiguousarray(cloud.T, np.float64)
    offsets = [np.take(column, nearest) - column[:, None] for column in columns]
    means = [np.sum(offset, axis=1) / count for offset in offsets]
    entries = np.empty((rows.size, 6), np.float64)
    for j, (a, b) in enumerate(_UPPER):
        products = np.einsum("ij,ij->i", offsets[a], offsets[b]) / count
        entries[:, j] = products - means[a] * means[b]
    out[slice(None) if rows.size == out.shape[0] else rows] = entries  # (no scatter: usual)
    return out


def _regularized(centre, neighbours, inside, valid):
    r"""$I - (1 - \varepsilon) n n^\top$ from the sample covariance of `neighbours` `(n, 3, k)`
    where `inside` `(n, k)`; the identity where fewer than 5 are inside or `valid` is False."""
    covariance, count = offset_covariances(neighbours - centre[:, :, None], inside)
    return _plane_regularized(covariance, count, valid)


def _plane_regularized(covariance, count, valid):
    r"""$I - (1 - \varepsilon) n n^\top$, $n$ the eigenvector of the smallest eigenvalue of each
    `(n, 3, 3)` covariance of `count` points; the identity where `count` is below 5 or `valid`
    is False."""
    normal = smallest_eigenvector(covariance)
    eye = jnp.eye(3, dtype=covariance.dtype)
    regularized = eye - (1.0 - EPSILON) * normal[:, :, None] * normal[:, None, :]
    return jnp.where((valid & (count >= MIN_NEIGHBOURS))[:, None, None], regularized, eye)


def default_covariances(points, mask, k, buckets):
    """`estimate_covariances` of a cloud; with `buckets`, on the cloud padded (masked rows) to its
    capacity bucket, as `_register` pads it (`lieax.icp._batch.bucket_size`), cut back to the
    cloud's rows: a cloud of a new size in a known bucket compiles nothing new."""
    if not buckets:
        return estimate_covariances(points, k=k, mask=mask)
    padded, padded_mask = pad_to_bucket(points, mask)
    covariances = estimate_covariances(padded, k=k, mask=padded_mask)
    if is_concrete(covariances):  # a transfer, not a compiled slice (`to_device`)
        return to_device(np.asarray(covariances)[: points.shape[0]])
    return covariances[: points.shape[0]]


def check_covariances(covariances, points, what):
    covariances = as_float_array(covariances, what)
    expected = (points.shape[0], 3, 3)
    if covariances.shape != expected:
        raise ValueError(
            f"{what} must have shape {expected} (one 3x3 matrix per point), "
            f"got shape {tuple(covariances.shape)}."
        )
    if covariances.dtype != points.dtype:
        raise TypeError(
            f"{what} must have the points' dtype {points.dtype}, got {covariances.dtype}."
        )
    return covariances
