r"""The pinhole camera (GTSAM's `PinholeCamera<Cal3_S2>` and `PinholeCamera<Cal3DS2>`):
projection and its closed-form Jacobians with respect to the pose, the point and the
calibration.

A world point $X$ is moved into the camera, $P = T_{wc}^{-1} X$ (`_frame`), projected on the
normalized image plane, $p = (P_x, P_y) / P_z$, then through the calibration,
$u = \kappa(p)$ (`_calibration`: `Cal3_S2` or `Cal3DS2`). The camera looks down its $+z$ axis:
points in front have depth $P_z > 0$. The chain (GTSAM's `PinholeCamera::project`,
`PinholeBase::Dpose` / `Dpoint`):
$$\frac{\partial p}{\partial P} = \frac{1}{P_z}\begin{bmatrix} 1 & 0 & -p_x \\ 0 & 1 & -p_y
\end{bmatrix}, \qquad
\frac{\partial u}{\partial \xi} = \frac{\partial \kappa}{\partial p}\frac{\partial p}{\partial P}
\begin{bmatrix} -I & [P]_\times \end{bmatrix}, \qquad
\frac{\partial u}{\partial X} = \frac{\partial \kappa}{\partial p}\frac{\partial p}{\partial P}
R^\top,$$
and $\partial u / \partial \kappa$ is the calibration's own block. These functions apply no
policy for points behind the camera ($P_z \le 0$, where GTSAM throws `CheiralityException`):
they return the mirrored projection, finite for $P_z \ne 0$. The factors (`projection_factor`)
apply the policy.
"""

import jax
import jax.numpy as jnp
from jax.typing import ArrayLike

from ..groups import SE3
from ._calibration import LAYOUTS, calibration_size, pixel, uncalibrate_jacobians
from ._frame import check_camera_inputs, in_camera, in_camera_jacobians


def _checked(entry, pose, calibration, point, measured=None):
    size = calibration_size(calibration, f"{entry}: calibration")
    extra = [(calibration, size, "calibration", LAYOUTS[size])]
    if measured is not None:
        extra.append((measured, 2, "measured", "u, v"))
    return check_camera_inputs(entry, pose, point, *extra)


def normalized_jacobian(P):
    r"""`(p, dp_dP)`: $p = P_{xy} / P_z$ and $\frac{1}{P_z}[I \mid -p]$, `(*batch, 2, 3)`."""
    inverse_depth = 1 / P[..., 2]
    p = P[..., :2] * inverse_depth[..., None]
    eye = jnp.broadcast_to(jnp.eye(2, dtype=P.dtype), p.shape[:-1] + (2, 2))
    dp_dP = inverse_depth[..., None, None] * jnp.concatenate([eye, -p[..., :, None]], -1)
    return p, dp_dP


def project(T_world_camera: SE3, calibration: ArrayLike, point: ArrayLike) -> jax.Array:
    r"""The pixel $u = \kappa(P_{xy}/P_z)$, $P = T_{wc}^{-1} X$, shape `(*batch, 2)` (GTSAM's
    `PinholeCamera::project`; module docstring).

    **Arguments:**

    - `T_world_camera`: `SE3`, camera to world.
    - `calibration`: `(*batch, 5)` `Cal3_S2` $(f_x, f_y, s, u_0, v_0)$ or `(*batch, 9)`
      `Cal3DS2` $(f_x, f_y, s, u_0, v_0, k_1, k_2, p_1, p_2)$.
    - `point`: `(*batch, 3)` world point $X$.

    Written with lieax operations (SE3's closed-form rules, then rational functions), so that
    `lieax.jacobian` differentiates it to `project_jacobians`' blocks; batch shapes broadcast.
    No cheirality check (module docstring).
    """
    point, calibration = _checked("project", T_world_camera, calibration, point)
    P = in_camera(T_world_camera, point)
    return pixel(calibration, P[..., :2] / P[..., 2:])


def project_jacobians(
    T_world_camera: SE3, calibration: ArrayLike, point: ArrayLike
) -> tuple[jax.Array, jax.Array, jax.Array, jax.Array]:
    r"""`(pixel, J_pixel_pose, J_pixel_point, J_pixel_calibration)` in closed form, shapes
    `(*batch, 2)`, `(*batch, 2, 6)` (tangent $(v, \omega)$, right perturbation), `(*batch, 2, 3)`
    and `(*batch, 2, n)` (module docstring). Arguments as `project`."""
    point, calibration = _checked("project_jacobians", T_world_camera, calibration, point)
    P, J_P_pose, J_P_point = in_camera_jacobians(T_world_camera, point)
    p, dp_dP = normalized_jacobian(P)
    pixel, J_calibration, J_pixel_p = uncalibrate_jacobians(calibration, p)
    J_pixel_P = J_pixel_p @ dp_dP
    batch = pixel.shape[:-1]
    return (
        pixel,
        jnp.broadcast_to(J_pixel_P @ J_P_pose, (*batch, 2, 6)),
        jnp.broadcast_to(J_pixel_P @ J_P_point, (*batch, 2, 3)),
        J_calibration,
    )
