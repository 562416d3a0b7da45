r"""Generalized ICP (plane-to-plane; Segal, Haehnel, Thrun, "Generalized-ICP", RSS 2009).

Every point carries a covariance of its local surface; a pair $(s_i, d_i)$ (source point, its
nearest target point) has the residual $r_i = T s_i - d_i$ and the Mahalanobis weight
$M_i = (C^d_i + R C^s_i R^\top)^{-1}$, and the pose minimizes $\sum_i \rho(r_i^\top M_i r_i)$.
It runs in the loop of `point_to_plane` (`lieax.icp._registration`: match, update, re-match, the
same statuses, stopping rule and exact check), with this module's Gauss-Newton update.

Conventions (right perturbation, translation-first tangents, `T_a_b` maps b into a) are the
README's "Conventions".
"""

import functools

import jax
import jax.numpy as jnp

from .._checks import as_float_array
from ..groups._se3 import SE3
from . import _neighbors, _normals, _search
from ._batch import pad_to_bucket
from ._checks import check_cloud, check_count, check_mask
from ._normals import _UPPER, offset_covariances, smallest_eigenvector
from ._registration import (
    ICPResult,
    _act_jacobian_rows,
    _register,
    _solve_spd,
    _transformed_columns,
)

EPSILON = 1e-3  # the smallest regularized eigenvalue (GICP, fast_gicp, small_gicp)
MIN_NEIGHBOURS = 5  # fewer valid neighbours give the identity (small_gicp's rule)


# ---- covariances --------------------------------------------------------------------------------


def estimate_covariances(points, *, k=20, mask=None, search="auto"):
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
    - `search`: how the neighbours are found, as for `estimate_normals`: `"kdtree"`, the host
      k-d tree (`lieax.icp._host_kdtree.nearest_valid_rows`: pykdtree's where it is installed,
      else SciPy's; exact; CPU only), `"graph"`, the fixed-shape neighbour graph (any backend;
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
        found = _normals.neighbourhoods(points, mask, k, search="kdtree")
        return _covariances_of_neighbours(points, mask, found)
    return _estimate(points, mask, k=k)


@functools.partial(jax.jit, static_argnames=("k",))
def _estimate(points, mask, *, k):
    safe = jnp.where(mask[:, None] & jnp.isfinite(points), points, 0.0)
    # 16 adjacent leaves of 16 points: 99.96% of the bunny's 20-neighbourhoods are exact (24 leaves:
    # 99.97%, at twice the build time; the rest swap a far neighbour for an almost as near one).
    index = _neighbors.build_index(safe, mask, degree=k - 1, links=0, adjacent_leaves=16)
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


@jax.jit
def _covariances_of_neighbours(points, mask, found):
    """The covariances over the neighbourhoods `found` (`-1` for none) of `_normals.neighbourhoods`
    (the host k-d tree's: exact)."""
    valid = mask & jnp.all(jnp.isfinite(points), axis=1)
    safe = jnp.where(valid[:, None], points, 0.0)
    neighbours = jnp.transpose(safe[jnp.maximum(found, 0)], (0, 2, 1))  # (n, 3, k)
    return _regularized(safe, neighbours, found >= 0, valid)


def _regularized(centre, neighbours, inside, valid):
    r"""$I - (1 - \varepsilon) n n^\top$ from the sample covariance of `neighbours` `(n, 3, k)`
    where `inside` `(n, k)`; the identity where fewer than 5 are inside or `valid` is False."""
    covariance, count = offset_covariances(neighbours - centre[:, :, None], inside)
    normal = smallest_eigenvector(covariance)
    eye = jnp.eye(3, dtype=centre.dtype)
    regularized = eye - (1.0 - EPSILON) * normal[:, :, None] * normal[:, None, :]
    return jnp.where((valid & (count >= MIN_NEIGHBOURS))[:, None, None], regularized, eye)


# ---- the update ---------------------------------------------------------------------------------


def _symmetric(matrix):
    """The six upper entries `(00, 01, 02, 11, 12, 22)` of `(n, 3, 3)` matrices, each `(n,)`."""
    return [matrix[:, a, b] for a, b in _UPPER]


def _entry(upper, a, b):
    return upper[_UPPER.index((min(a, b), max(a, b)))]


def _mahalanobis(rotation, source_covariances, target_covariances):
    r"""$M_i = (C^d_i + R C^s_i R^\top)^{-1}$ as six `(n,)` entries, written out elementwise: the
    rotated covariance entry by entry, then the symmetric inverse by cofactors,
    $S^{-1} = \mathrm{adj}(S) / \det S$."""
    cs = _symmetric(source_covariances)
    cd = _symmetric(target_covariances)
    # B = R C^s (3 x 3), then S = C^d + B R^T (upper entries).
    b = [[sum(rotation[a, j] * _entry(cs, j, c) for j in range(3)) for c in range(3)] for a in
         range(3)]  # fmt: skip
    s = [_entry(cd, a, c) + sum(b[a][j] * rotation[c, j] for j in range(3)) for a, c in _UPPER]
    s00, s01, s02, s11, s12, s22 = s
    c00 = s11 * s22 - s12 * s12
    c01 = s02 * s12 - s01 * s22
    c02 = s01 * s12 - s02 * s11
    c11 = s00 * s22 - s02 * s02
    c12 = s01 * s02 - s00 * s12
    c22 = s00 * s11 - s01 * s01
    det = s00 * c00 + s01 * c01 + s02 * c02
    return [c / det for c in (c00, c01, c02, c11, c12, c22)]


def gicp_normal_equations(params, source, matched, source_covariances, target_covariances, weights):
    r"""$H = \sum_i w_i J_i^\top M_i J_i$, $g = \sum_i w_i J_i^\top M_i r_i$ and the costs
    $r_i^\top M_i r_i$ of the GICP residuals $r_i = T s_i - d_i$ at `params`, with
    $J_i = \partial (T \oplus \xi) s_i / \partial \xi = [R, -R[s_i]_\times]$ (from
    `lieax.jacobian` of `SE3`'s action, see `_act_jacobian_rows`) and $M_i$ held fixed
    (`_mahalanobis` at the current rotation, as small_gicp recomputes it per linearization).
    `weights` (`(n,)`, or a function of the costs) are the pair weights (0 for rejected pairs).

    **Returns:** `(H (6, 6), g (6,), costs (n,))`.
    """
    pose = SE3._wrap(params)
    rotation = pose.rotation().as_matrix()
    m = _mahalanobis(rotation, source_covariances, target_covariances)
    moved = _transformed_columns(params, source)
    r = [moved[a] - matched[:, a] for a in range(3)]
    mr = [sum(_entry(m, a, b) * r[b] for b in range(3)) for a in range(3)]
    costs = sum(r[a] * mr[a] for a in range(3))
    if callable(weights):
        weights = weights(costs)
    constant, slope = _act_jacobian_rows(pose, source)
    # Row a of every pair's J_i, transposed: (6, n) each (contiguous rows, no transposes for the
    # products below; `_registration._plane_rows` says why).
    rows = [constant[a][:, None] + sum(slope[k, a][:, None] * source[:, k] for k in range(3)) for
            a in range(3)]  # fmt: skip
    m_rows = [sum(_entry(m, a, b) * rows[b] for b in range(3)) for a in range(3)]
    jac_t = jnp.concatenate(rows, axis=1)  # (6, 3n): row a of every pair, then the next row
    weighted = jnp.concatenate([weights * m_rows[a] for a in range(3)], axis=1)
    weighted_mr = jnp.concatenate([weights * mr[a] for a in range(3)])
    hessian = jnp.matmul(weighted, jac_t.T, precision=jax.lax.Precision.HIGHEST)
    gradient = jnp.matmul(jac_t, weighted_mr, precision=jax.lax.Precision.HIGHEST)
    return 0.5 * (hessian + hessian.T), gradient, costs


def gicp_step(
    params, source, matched, source_covariances, target_covariances, inliers, loss_weights
):  # fmt: skip
    r"""One Gauss-Newton step $T \leftarrow T \oplus \delta$, $\delta = -H^{-1} g$ (see
    `gicp_normal_equations`), with the IRLS weights $w_i = \rho'(r_i^\top M_i r_i)$ of the
    inlier pairs; rejected pairs get identity covariances (any finite value: their weight is 0)."""
    eye = jnp.eye(3, dtype=params.dtype)
    source_covariances = jnp.where(inliers[:, None, None], source_covariances, eye)
    target_covariances = jnp.where(inliers[:, None, None], target_covariances, eye)
    hessian, gradient, _ = gicp_normal_equations(
        params, source, matched, source_covariances, target_covariances,
        lambda costs: inliers.astype(params.dtype) * loss_weights(costs),
    )  # fmt: skip
    step = -_solve_spd(hessian, gradient)
    return SE3._wrap(params).rplus(step).parameters()


# ---- entry point --------------------------------------------------------------------------------


def gicp(
    source,
    target,
    *,
    max_correspondence_distance,
    source_covariances=None,
    target_covariances=None,
    init=None,
    max_iterations=30,
    relative_fitness=1e-6,
    relative_rmse=1e-6,
    loss=None,
    source_mask=None,
    target_mask=None,
    exact=True,
    covariances_k=20,
    verbose=False,
    throw=True,
    search="auto",
    buckets=True,
) -> ICPResult:
    r"""Generalized ICP: minimize
    $\sum_i \rho\big(r_i^\top (C^d_i + R C^s_i R^\top)^{-1} r_i\big)$, $r_i = T s_i - d_i$,
    over $T$ = `T_target_source`, re-matching $d_i$ (nearest target point of $T s_i$) every
    iteration; one Gauss-Newton step per iteration (see `gicp_step`).

    The loop, the statuses, the errors and the stopping rule are those of `point_to_plane`: stop
    when the fitness and the inlier RMSE both changed by less than `relative_fitness` and
    `relative_rmse` (Open3D's rule). small_gicp stops on the size of the step instead (0.1° and
    1 mm, an absolute translation that suits metre-scale scans only); this rule needs no scale
    and is the shared loop's. It costs iterations: 13 against small_gicp's 9 on the LiDAR scans,
    15 against 13 on the full bunny, about as many on the others (see `benchmarks/gicp.py`).

    **Arguments:**
    - `source`, `target`: clouds of shape `(n, 3)` and `(m, 3)`, the same floating dtype.
    - `max_correspondence_distance`: pairs farther apart are rejected (masked).
    - `source_covariances`, `target_covariances`: `(n, 3, 3)`, `(m, 3, 3)` symmetric positive
      definite; default `estimate_covariances(cloud, k=covariances_k)`.
    - `init`: initial `SE3` guess of `T_target_source` (default identity).
    - `max_iterations`: most pose updates.
    - `relative_fitness`, `relative_rmse`: the stopping tolerances (absolute changes).
    - `loss`: robust loss with a `weight(s)` method of the squared Mahalanobis residual (the
      `lieax.lstsq` losses); default least squares.
    - `source_mask`, `target_mask`: `(n,)`, `(m,)` bools, False for padding (see `pad_clouds`).
    - `exact`: verify the final matches with an exact search (as `point_to_plane`).
    - `covariances_k`: neighbours for the default covariances (small_gicp's default, 20), found
      as `search` says (`"auto"`: see `estimate_covariances`).
    - `verbose`: print the fitness and inlier RMSE after every iteration.
    - `throw`: as for `point_to_plane` (raise `ICPError` for a `NONFINITE`, `INVALID` or
      `DEGENERATE` result; under `jit` when the program runs, under `vmap` never).
    - `search`: the correspondence search, as for `point_to_plane`.
    - `buckets`: pad the clouds (and the default covariances' clouds) to capacity buckets, as for
      `point_to_plane`.

    Derivatives through `gicp` raise `NotImplementedError` (the implicit derivatives of
    `lieax.icp._implicit` cover point-to-point and point-to-plane).

    **Returns:** an `ICPResult`.
    """
    source = check_cloud(source, "source")
    target = check_cloud(target, "target")
    source_mask = check_mask(source_mask, source, "source_mask")
    target_mask = check_mask(target_mask, target, "target_mask")
    if source_covariances is None:
        source_covariances = _default_covariances(source, source_mask, covariances_k, buckets)
    if target_covariances is None:
        target_covariances = _default_covariances(target, target_mask, covariances_k, buckets)
    source_covariances = _check_covariances(source_covariances, source, "source_covariances")
    target_covariances = _check_covariances(target_covariances, target, "target_covariances")
    return _register(
        "gicp", source, target, max_correspondence_distance, None, init, max_iterations,
        relative_fitness, relative_rmse, loss, source_mask, target_mask, exact, 0, verbose, throw,
        search=search, source_covariances=source_covariances,
        target_covariances=target_covariances, buckets=buckets,
    )  # fmt: skip


def _default_covariances(points, mask, k, buckets):
    """`estimate_covariances` of a cloud; with `buckets`, on the cloud padded (masked rows) to its
    capacity bucket, as `_register` pads it (`lieax.icp._batch.bucket_size`), cut back to the
    cloud's rows: a cloud of a new size in a known bucket compiles nothing new."""
    if not buckets:
        return estimate_covariances(points, k=k, mask=mask)
    padded, padded_mask = pad_to_bucket(points, mask)
    return estimate_covariances(padded, k=k, mask=padded_mask)[: points.shape[0]]


def _check_covariances(covariances, points, what):
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
