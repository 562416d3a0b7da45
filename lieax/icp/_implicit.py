r"""Derivatives of a converged ICP pose by the implicit function theorem; the loop is never
differentiated (its inputs reach it through `lax.stop_gradient`).

With its final matches $c_i$ held fixed, a converged pose $T^*$ is a stationary point of the
robust cost $f(T; \theta) = \tfrac12 \sum_{i \in I} \rho(\|r_i(T; \theta)\|^2)$ over the inlier
pairs $I$, with

- point-to-plane: $r_i = n_{c_i}^\top (T s_i - d_{c_i})$ (one row per pair),
- point-to-point: $r_i = T s_i - d_{c_i}$ (three rows; the weighted Kabsch step is the exact
  minimizer of this cost for fixed weights),

and the data $\theta$ = (`source` $s$, `target` $d$, `target_normals` $n$, the loss's scale).
Its tangent gradient $g(\delta; \theta) = \nabla_\delta f(T^* \oplus \delta; \theta) = J^\top W r$,
$W = \rho'(\|r_i\|^2)$ (the IRLS weights, as functions of the residuals: a fixed point of
iteratively reweighted least squares is a stationary point of $f$), vanishes at $\delta = 0$.
The implicit function theorem (Ceres Solver's notes, "Using Inverse & Implicit Function
Theorems") gives the right-local tangent of the pose

$$\dot\delta = -H^{-1}\,\frac{\partial g}{\partial \theta}\,\dot\theta, \qquad
H = \frac{\partial g}{\partial \delta}\Big|_{\delta = 0}$$

(the exact Hessian of $f$, so nonzero residuals get exact derivatives). What is held fixed:

- the matches and the inlier set: piecewise constant in $\theta$ (they change only where a
  nearest neighbour or the `max_correspondence_distance` test switches), so this is the
  derivative wherever one exists; `max_correspondence_distance` and the tolerances get zero.
- the target normals, when `point_to_plane` estimates them (`target_normals=None`): they move
  with the target, their neighbourhoods held fixed (`estimated_normals`).
- `init`: zero. The converged pose is a minimizer of the cost of its matches, which does not
  depend on where the iterations started (a small change of `init` leads to the same matches
  and the same minimizer).

The other outputs: `inlier_rmse` $= (\tfrac1{|I|} \sum_{i \in I} \|T^* s_i - d_{c_i}\|^2)^{1/2}$
is differentiated through $T^*$ and the data with the inliers fixed; `fitness`, `iterations`,
`status` and `correspondences` are piecewise constant (zero derivative).

Only a `CONVERGED` run is a stationary point. For any other status the derivative is undefined:
outside `jit`/`vmap` (a concrete status) differentiating raises `ICPError` (with `throw=True`);
inside, or with `throw=False`, the pose's and the RMSE's tangents are NaN for exactly those
problems (a `vmap`ped batch keeps the others' derivatives). The derivative is that of the exact
stationary point: it matches finite differences of the returned pose to the accuracy to which
the loop converged (tighten `relative_fitness`/`relative_rmse` to compare them closely).

The rule is `lieax.lstsq._implicit.stationary_tangent`, the one of `lieax.lstsq`'s implicit
derivatives: linear in $\dot\theta$ (one Hessian, a forward pass of $g$, a 6x6 solve), so JAX
transposes it for `jax.grad`.
"""

import functools

import jax
import jax.numpy as jnp

from .._linalg import quat_to_matrix
from ..groups import SE3, kernels
from ..lstsq._implicit import stationary_tangent
from ..lstsq._solution import Status
from ._centring import centred_pose, centroid, uncentred_tangent
from ._checks import ICPError
from ._normals import neighbourhood_covariances, neighbourhoods, normals_from_neighbourhoods
from ._robust import loss_weights


def with_implicit_derivatives(kind, static_loss, throw, result, data, fixed):
    """`result` (an `ICPResult` of the loop run on constant inputs) whose `transform` and
    `inlier_rmse` carry the implicit derivatives with respect to
    `data = (source, target, target_normals, loss_scale, other)`, `fixed = (source_mask,
    loss_kind)` (`target_normals` is None for point-to-point, `loss_kind` None for a static loss,
    `other` the data of other kinds, whose derivatives raise)."""
    params, rmse = _converged(
        kind, static_loss, throw, result.transform.parameters(), result.inlier_rmse, data,
        (result.correspondences, result.status, *fixed),
    )  # fmt: skip
    return result._replace(transform=kernels.element(SE3, params), inlier_rmse=rmse)


@functools.partial(jax.custom_jvp, nondiff_argnums=(0, 1, 2))
def _converged(kind, static_loss, throw, params, rmse, data, fixed):
    return params, rmse


@_converged.defjvp
def _converged_jvp(kind, static_loss, throw, primals, tangents):
    params, rmse, data, fixed = primals
    _, _, data_dot, _ = tangents
    if kind not in ("plane", "point"):
        raise NotImplementedError(
            f"derivatives through ICP of kind {kind!r} are not implemented (point_to_plane and "
            "point_to_point have them); differentiate a lieax.lstsq solve on its final matches."
        )
    status = fixed[1]
    if throw and not isinstance(status, jax.core.Tracer) and int(status) != Status.CONVERGED:
        raise ICPError(
            f"the derivative of an ICP result is defined only at a converged run; this one ended "
            f"{Status(int(status)).name} (raise max_iterations, check the data, or pass "
            "throw=False for NaN derivatives)."
        )
    tangents_out = _tangents(
        params, rmse, data, fixed, data_dot, kind=kind, static_loss=static_loss
    )
    return (params, rmse), tangents_out


@functools.partial(jax.jit, static_argnames=("kind", "static_loss"))
def _tangents(params, rmse, data, fixed, data_dot, *, kind, static_loss):
    """`(pose tangent, inlier RMSE tangent)` for the data tangent `data_dot` (see the module
    docstring)."""
    correspondences, status, source_mask, loss_kind = fixed
    inliers = (correspondences >= 0) & source_mask
    index = jnp.maximum(correspondences, 0)
    count = jnp.maximum(jnp.sum(inliers), 1)
    # Centred as the loop is (`lieax.icp._centring`): the Hessian of clouds far from the origin is
    # then as well conditioned as at the origin. The centres are constants of the rule.
    source_centre = centroid(data[0], inliers)
    target_centre = centroid(data[1][index], inliers)
    centred = centred_pose(params, source_centre, target_centre)

    def gaps(delta, data):
        r"""$T' \oplus \delta$ (the centred pose) applied to the inlier source points about their
        centre, minus their matches about theirs (rows of rejected points are zero, whatever the
        data hold there)."""
        source, target = data[:2]
        source = jnp.where(inliers[:, None], source - source_centre, 0.0)
        matched = jnp.where(inliers[:, None], target[index] - target_centre, 0.0)
        pose = kernels.element(SE3, centred).rplus(delta).parameters()
        moved = jnp.matmul(source, quat_to_matrix(pose[:4]).T, precision="highest") + pose[4:]
        return jnp.where(inliers[:, None], moved - matched, 0.0)

    def residuals(delta, data):
        gap = gaps(delta, data)
        if kind == "plane":
            normals = jnp.where(inliers[:, None], data[2][index], 0.0)
            residual = jnp.sum(normals * gap, axis=-1)
            return residual, residual * residual
        return gap, jnp.sum(gap * gap, axis=-1)

    def gradient(delta, data):
        r"""$g = J^\top W r$, $W = \rho'(\|r_i\|^2)$ at $\delta$: the gradient of
        $\tfrac12 \sum_i \rho(\|r_i\|^2)$ (the weights are not differentiated by the pullback)."""
        (residual, squared), pullback = jax.vjp(lambda d: residuals(d, data), delta)
        loss = None if loss_kind is None else (loss_kind, data[3])
        weights = inliers.astype(residual.dtype) * loss_weights(loss, static_loss, squared)
        weighted = weights * residual if kind == "plane" else weights[:, None] * residual
        return pullback((weighted, jnp.zeros_like(squared)))[0]

    # NaN where the run did not converge: a constant factor on the data tangent and on the
    # results, so that the cotangents of reverse mode (the transposed rule) are NaN there too.
    undefined = jnp.where(status == Status.CONVERGED, 1.0, jnp.nan).astype(params.dtype)
    data_dot = jax.tree.map(lambda x: x * undefined.astype(x.dtype), data_dot)
    zero = jnp.zeros((6,), params.dtype)
    hessian = jax.jacfwd(gradient)(zero, data)
    _, mixed = jax.jvp(lambda d: gradient(zero, d), (data,), (data_dot,))
    delta_dot = stationary_tangent(hessian, mixed) * undefined

    def mean_squared(delta, data):
        gap = gaps(delta, data)
        return jnp.sum(gap * gap) / count

    _, mean_squared_dot = jax.jvp(mean_squared, (zero, data), (delta_dot, data_dot))
    # d sqrt(m) = dm / (2 sqrt(m)); an exact fit (rmse 0) has zero gaps, and a zero derivative.
    rmse_dot = jnp.where(rmse > 0, mean_squared_dot / (2 * jnp.where(rmse > 0, rmse, 1.0)), 0.0)
    delta_dot = uncentred_tangent(delta_dot, source_centre)
    return SE3._tangent_from_local(params, delta_dot), rmse_dot.astype(rmse.dtype) * undefined


def estimated_normals(target, mask, k):
    r"""`estimate_normals(target, k=k, mask=mask)`, differentiable with respect to `target` by
    the perturbation of an eigenvector: for the normal $n$ (eigenvalue $\lambda$) of the
    neighbourhood covariance $C$, $\dot n = -(C - \lambda I)^{+}\,\dot C\,n$ (first-order
    perturbation theory of a simple eigenvalue; e.g. Magnus, "On differentiating eigenvalues and
    eigenvectors", 1985), with the neighbourhoods and the viewpoint flip held fixed."""
    fixed = jax.lax.stop_gradient(target)
    found = neighbourhoods(fixed, mask, k)
    normals = normals_from_neighbourhoods(fixed, mask, found)
    return _normals_of(target, mask, found, normals)


@jax.custom_jvp
def _normals_of(target, mask, found, normals):
    return normals


@_normals_of.defjvp
def _normals_of_jvp(primals, tangents):
    target, mask, found, normals = primals
    target_dot = tangents[0]
    return normals, _normals_tangent(target, mask, found, normals, target_dot)


@jax.jit
def _normals_tangent(target, mask, found, normal, target_dot):
    r"""$\dot n$ for every point, over the neighbourhoods `found` (from `neighbourhoods`, as
    `estimate_normals` uses them); rows with fewer than 3 valid neighbours (the constant fallback
    normal) and padding get zero."""
    valid_rows = mask & jnp.all(jnp.isfinite(target), axis=1)
    safe = jnp.where(valid_rows[:, None], target, 0.0)
    count = jnp.sum(found >= 0, axis=1)

    def covariance(points):
        return neighbourhood_covariances(points, found)[0]

    matrix, matrix_dot = jax.jvp(
        covariance, (safe,), (jnp.where(valid_rows[:, None], target_dot, 0.0),)
    )
    # (C - λI)^+ = (C - λI + c n nᵀ)^{-1} - n nᵀ / c for the unit null vector n of C - λI, with
    # c = tr C (any c > 0; this one keeps the matrix at the scale of C).
    eigenvalue = jnp.einsum("si,sij,sj->s", normal, matrix, normal)
    scale = jnp.trace(matrix, axis1=1, axis2=2)
    usable = valid_rows & (count >= 3) & (scale > 0)
    scale = jnp.where(usable, scale, 1.0)
    outer = normal[:, :, None] * normal[:, None, :]
    eye = jnp.eye(3, dtype=target.dtype)
    shifted = jnp.where(
        usable[:, None, None], matrix - eigenvalue[:, None, None] * eye + scale[:, None, None] * outer,
        eye,
    )  # fmt: skip
    pushed = jnp.einsum("sij,sj->si", matrix_dot, normal)
    normal_dot = -(jnp.linalg.solve(shifted, pushed[:, :, None])[:, :, 0]
                   - normal * jnp.sum(normal * pushed, axis=1, keepdims=True) / scale[:, None])  # fmt: skip
    return jnp.where(usable[:, None], normal_dot, 0.0)
