r"""Between and prior residuals of SE2/SE3 poses with their closed-form Jacobian blocks.

Between factor (GTSAM's `BetweenFactor`): with $H = X_i^{-1} X_j$ and $E = Z^{-1} H$,
$$e = \mathrm{Log}(E), \qquad
\frac{\partial e}{\partial X_j} = J_r^{-1}(e), \qquad
\frac{\partial e}{\partial X_i} = -J_r^{-1}(e)\,\mathrm{Ad}(H^{-1}) = -J_r^{-1}(e)\,\mathrm{Ad}(X_j^{-1} X_i).$$
(Right perturbations: $X_j \oplus \delta$ gives $E\,\mathrm{Exp}(\delta)$; $X_i \oplus \delta$ gives
$Z^{-1}\mathrm{Exp}(-\delta) H = E\,\mathrm{Exp}(-\mathrm{Ad}(H^{-1})\delta)$; then
$\mathrm{Log}(E\,\mathrm{Exp}(\delta)) \approx e + J_r^{-1}(e)\,\delta$.) The measurement sits left of
$H$, so the adjoint is that of $H^{-1}$, not of $E^{-1}$.

GTSAM's `BetweenFactor` built without `GTSAM_SLOW_BUT_CORRECT_BETWEENFACTOR` drops $J_r^{-1}(e)$: its
blocks are then $-\mathrm{Ad}(H^{-1})$ and $I$, the Jacobians of `between` "before the Log" (Jeong,
"GTSAM tutorial 6", eq. 7). Both weigh the same error, so the cost is the same function;
`exact=False` gives those blocks, `exact=True` (the default of `lieax.graph.optimize`) the true
Jacobian, whose fixed points are the cost's stationary points (GTSAM 4.3's pip wheels follow these
iterates: same iteration counts and final costs on the shared g2o sets).

Prior factor (GTSAM's `PriorFactor`): $e = \mathrm{Log}(Z^{-1} X)$, $\partial e / \partial X = J_r^{-1}(e)$
($I$ in GTSAM).
"""

import jax
import jax.numpy as jnp

from ..groups import SE2, SE3, AbstractGroup
from ._graph import PoseGraph


def between_error(
    pose_i: AbstractGroup, pose_j: AbstractGroup, measured: AbstractGroup
) -> jax.Array:
    r"""$\mathrm{Log}(Z^{-1} X_i^{-1} X_j)$, batched; the residual before whitening."""
    return measured.between(pose_i.between(pose_j)).log()


def between_jacobians(
    pose_i: AbstractGroup, pose_j: AbstractGroup, measured: AbstractGroup, exact: bool = True
) -> tuple[jax.Array, jax.Array, jax.Array]:
    r"""`(e, J_e_pose_i, J_e_pose_j)`: the error and its `(..., d, d)` blocks (see the module
    docstring; `exact=False` gives GTSAM's blocks $-\mathrm{Ad}(H^{-1})$ and $I$)."""
    relative = pose_i.between(pose_j)
    error = measured.between(relative).log()
    adjoint = relative.inverse().adjoint()
    if exact:
        J_e_pose_j = type(relative).right_jacobian_inverse(error)
        J_e_pose_i = -J_e_pose_j @ adjoint
    else:
        J_e_pose_j = jnp.broadcast_to(jnp.eye(error.shape[-1], dtype=error.dtype), adjoint.shape)
        J_e_pose_i = -adjoint
    return error, J_e_pose_i, J_e_pose_j


def prior_error(pose: AbstractGroup, measured: AbstractGroup) -> jax.Array:
    r"""$\mathrm{Log}(Z^{-1} X)$."""
    return measured.between(pose).log()


def prior_jacobian(
    pose: AbstractGroup, measured: AbstractGroup, exact: bool = True
) -> tuple[jax.Array, jax.Array]:
    """`(e, J_e_pose)` with $J = J_r^{-1}(e)$ (`exact`) or $I$ (GTSAM)."""
    error = prior_error(pose, measured)
    if exact:
        return error, type(pose).right_jacobian_inverse(error)
    eye = jnp.eye(error.shape[-1], dtype=error.dtype)
    return error, jnp.broadcast_to(eye, (*error.shape, error.shape[-1]))


def whiten(sqrt_information, error):
    r"""$R\,e$ for `(..., d, d)` and `(..., d)`."""
    return jnp.einsum("...ab,...b->...a", sqrt_information, error)


def robust_weights(loss, squared_norm):
    r"""$\rho(s)$ and $\rho'(s)$ of the whitened squared norms (`(s, 1)` without a loss)."""
    if loss is None:
        return squared_norm, jnp.ones_like(squared_norm)
    return loss(squared_norm), loss.weight(squared_norm)


def between_cost(graph_between, poses):
    r"""$\tfrac12 \sum \rho(\|R e\|^2)$ over the between factors at `poses`."""
    f = graph_between
    e = between_error(poses[f.i], poses[f.j], f.measured)
    s = jnp.sum(whiten(f.sqrt_information, e) ** 2, axis=-1)
    return 0.5 * jnp.sum(robust_weights(f.loss, s)[0])


def prior_cost(priors, poses):
    if priors is None or len(priors) == 0:
        return jnp.zeros((), poses.dtype)
    e = prior_error(poses[priors.index], priors.measured)
    s = jnp.sum(whiten(priors.sqrt_information, e) ** 2, axis=-1)
    return 0.5 * jnp.sum(robust_weights(priors.loss, s)[0])


def cost(graph: PoseGraph, poses: SE2 | SE3 | None = None) -> jax.Array:
    r"""The graph's cost $\tfrac12 \sum \rho(r^\top \Omega r)$ at `poses` (default `graph.poses`):
    the quantity GTSAM's `graph.error(values)` reports (without robust losses)."""
    poses = graph.poses if poses is None else poses
    return between_cost(graph.between, poses) + prior_cost(graph.priors, poses)
