r"""Snavely's camera (Bundler, "Bundle Adjustment in the Large"): projection, reprojection residual
and its closed-form Jacobian blocks.

A camera is `(T_camera_world: SE3, intrinsics)` with intrinsics $(f, k_1, k_2)$; its tangent has 9
coordinates, the SE3 right perturbation $(v, \omega)$ (translation first, as everywhere in lieax)
then additive $(\delta f, \delta k_1, \delta k_2)$. A world point $X$ projects as (Snavely
et al., "Photo tourism", 2006; Agarwal et al., "Bundle adjustment in the large", 2010; Ceres'
`SnavelyReprojectionError`)
$$P = R X + t, \qquad p = -P_{xy} / P_z, \qquad r(p) = 1 + k_1\|p\|^2 + k_2\|p\|^4, \qquad
u = f\,r(p)\,p,$$
and the residual of an observation $u_{obs}$ is $u - u_{obs}$ (pixels, origin at the image centre).
The camera looks down its $-z$ axis: points in front have $P_z < 0$. As in Ceres nothing special is
done for points behind the camera ($P_z > 0$ projects through the centre, mirrored) or on its
plane: the residual and its Jacobians are finite for every $P_z \ne 0$ and infinite or NaN at
$P_z = 0$.

The BAL file's 9-number cameras convert with `lieax.ba.bal_to_camera` / `camera_to_bal`. Moved here
from `lieax.ba`, which re-exports these functions under their old names.
"""

import jax
import jax.numpy as jnp
from jax.typing import ArrayLike

from .._checks import broadcast_batch, check_last_axis
from ..groups import SE3, SO3


def check_pose(pose):
    if not isinstance(pose, SE3):
        raise TypeError(f"pose must be a lieax.SE3 (T_camera_world), got {type(pose).__name__}.")


def _check_inputs(pose, intrinsics, point, observation=None):
    check_pose(pose)
    intrinsics = check_last_axis(intrinsics, 3, "intrinsics", "f, k1, k2")
    point = check_last_axis(point, 3, "point")
    shapes = [pose.batch_shape, intrinsics.shape[:-1], point.shape[:-1]]
    if observation is not None:
        observation = check_last_axis(observation, 2, "observation", "u, v")
        shapes.append(observation.shape[:-1])
    broadcast_batch("reprojection", *shapes)
    return intrinsics, point, observation


def project(pose: SE3, intrinsics: ArrayLike, point: ArrayLike) -> jax.Array:
    r"""The pixel $u = f\,r(p)\,p$ of a world point, $p = -P_{xy}/P_z$, $P = T_{cw} X$ (see the
    module docstring), written with lieax operations so that `lieax.jacobian` differentiates it
    through SE3's closed-form action rule. Batch shapes broadcast."""
    intrinsics, point, _ = _check_inputs(pose, intrinsics, point)
    P = pose @ point
    p = -P[..., :2] / P[..., 2:]
    s = jnp.sum(p * p, axis=-1, keepdims=True)
    f, k1, k2 = intrinsics[..., 0:1], intrinsics[..., 1:2], intrinsics[..., 2:3]
    return f * (1 + s * (k1 + k2 * s)) * p


def reprojection_residual(
    pose: SE3, intrinsics: ArrayLike, point: ArrayLike, observation: ArrayLike
) -> jax.Array:
    """$u - u_{obs}$, the `(*batch, 2)` reprojection error of Snavely's camera (Ceres'
    `SnavelyReprojectionError`).

    **Arguments:**

    - `pose`: `SE3` $T_{cw}$ mapping world points into the camera.
    - `intrinsics`: `(*batch, 3)` $(f, k_1, k_2)$.
    - `point`: `(*batch, 3)` world point $X$.
    - `observation`: `(*batch, 2)` observed pixel $u_{obs}$.

    **Returns:** the residual; batch shapes broadcast. Written with lieax operations, so
    `lieax.jacobian(reprojection_residual, (0, 1, 2))` gives the blocks of
    `reprojection_jacobians`.
    """
    _check_inputs(pose, intrinsics, point, observation)
    return project(pose, intrinsics, point) - observation


def reprojection_jacobians(
    pose: SE3, intrinsics: ArrayLike, point: ArrayLike, observation: ArrayLike
) -> tuple[jax.Array, jax.Array, jax.Array, jax.Array]:
    r"""`(residual, J_res_pose, J_res_intrinsics, J_res_point)` in closed form, shapes
    `(*batch, 2)`, `(*batch, 2, 6)`, `(*batch, 2, 3)`, `(*batch, 2, 3)`.

    With right perturbation $T \oplus \xi = T\,\mathrm{Exp}(\xi)$, $\xi = (v, \omega)$:
    $T\,\mathrm{Exp}(\xi) X \approx P + R v - R [X]_\times \omega$, so
    $\partial P / \partial \xi = [R, \; -R[X]_\times]$ and $\partial P / \partial X = R$
    (Solà et al., "A micro Lie theory", eq. 181-182). The chain is
    $$\frac{\partial p}{\partial P} = -\frac{1}{P_z}\begin{bmatrix} 1 & 0 & p_x \\
    0 & 1 & p_y \end{bmatrix}, \qquad
    \frac{\partial u}{\partial p} =
    f\left(r\,I + 2 (k_1 + 2 k_2 \|p\|^2)\, p p^\top\right),$$
    $$\frac{\partial u}{\partial (f, k_1, k_2)} = \left[r\,p, \; f\|p\|^2 p, \;
    f\|p\|^4 p\right],$$
    and `J_res_pose` $= \frac{\partial u}{\partial P}[R, -R[X]_\times]$, `J_res_point`
    $= \frac{\partial u}{\partial P} R$ with $\frac{\partial u}{\partial P} =
    \frac{\partial u}{\partial p}\frac{\partial p}{\partial P}$. The camera's 2×9 block is
    `concatenate([J_res_pose, J_res_intrinsics], -1)`.

    **Arguments:** as `reprojection_residual`.
    """
    intrinsics, point, observation = _check_inputs(pose, intrinsics, point, observation)
    R = pose.rotation().as_matrix()
    P = jnp.einsum("...ij,...j->...i", R, point) + pose.translation()
    inverse_depth = 1 / P[..., 2]
    p = -P[..., :2] * inverse_depth[..., None]
    s = jnp.sum(p * p, axis=-1)
    f, k1, k2 = intrinsics[..., 0], intrinsics[..., 1], intrinsics[..., 2]
    radial = 1 + s * (k1 + k2 * s)
    residual = (f * radial)[..., None] * p - observation

    # du/dp, then du/dP = du/dp · dp/dP with dp/dP = -(1/P_z) [I | p]
    eye = jnp.eye(2, dtype=p.dtype)
    outer = p[..., :, None] * p[..., None, :]
    du_dp = f[..., None, None] * (
        radial[..., None, None] * eye + (2 * (k1 + 2 * k2 * s))[..., None, None] * outer
    )
    dp_dP = -inverse_depth[..., None, None] * jnp.concatenate(
        [jnp.broadcast_to(eye, p.shape[:-1] + (2, 2)), p[..., :, None]], axis=-1
    )
    du_dP = du_dp @ dp_dP
    J_res_point = du_dP @ R
    J_res_pose = jnp.concatenate([J_res_point, -J_res_point @ SO3.hat(point)], axis=-1)
    J_res_intrinsics = jnp.stack(
        [radial[..., None] * p, (f * s)[..., None] * p, (f * s * s)[..., None] * p], axis=-1
    )
    batch = residual.shape[:-1]
    return (
        residual,
        jnp.broadcast_to(J_res_pose, (*batch, 2, 6)),
        jnp.broadcast_to(J_res_intrinsics, (*batch, 2, 3)),
        jnp.broadcast_to(J_res_point, (*batch, 2, 3)),
    )


def camera_residual(
    camera: tuple[SE3, ArrayLike], point: ArrayLike, observation: ArrayLike
) -> jax.Array:
    r"""`reprojection_residual` with the camera as one variable `(T_camera_world, intrinsics)`,
    whose 9-coordinate tangent is the pose's $(v, \omega)$ then $(f, k_1, k_2)$: the residual of
    ONE camera and ONE point, as a factor graph's factor takes it."""
    pose, intrinsics = camera
    return reprojection_residual(pose, intrinsics, point, observation)


def camera_jacobians(
    camera: tuple[SE3, ArrayLike], point: ArrayLike, observation: ArrayLike
) -> tuple[jax.Array, tuple[jax.Array, jax.Array]]:
    """`(residual, (J_res_camera, J_res_point))` of `camera_residual` in closed form, blocks
    `(*batch, 2, 9)` and `(*batch, 2, 3)` (`reprojection_jacobians`' pose and intrinsics blocks
    side by side): the `jacobian_fn` of a factor graph's factor."""
    pose, intrinsics = camera
    residual, J_res_pose, J_res_intrinsics, J_res_point = reprojection_jacobians(
        pose, intrinsics, point, observation
    )
    return residual, (jnp.concatenate([J_res_pose, J_res_intrinsics], axis=-1), J_res_point)
