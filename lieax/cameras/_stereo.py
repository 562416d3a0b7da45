r"""The rectified stereo camera (GTSAM's `StereoCamera` with `Cal3_S2Stereo`): projection to
$(u_L, u_R, v)$ and its closed-form Jacobians.

The calibration is GTSAM's `Cal3_S2Stereo::vector()`, 6 numbers $(f_x, f_y, s, u_0, v_0, b)$,
$b$ the baseline; the pose $T_{wc}$ is the LEFT camera's, the right one sits at $(b, 0, 0)$ in
the left frame. With $P = T_{wc}^{-1} X$ (`_frame`) and $d = 1 / P_z$ (GTSAM's
`StereoCamera::project2`):
$$u_L = u_0 + f_x P_x d, \qquad u_R = u_0 + f_x (P_x - b) d, \qquad v = v_0 + f_y P_y d.$$
As in GTSAM the skew $s$ is carried but not used (its Jacobian column is zero). Blocks:
$$\frac{\partial (u_L, u_R, v)}{\partial P} = d\begin{bmatrix} f_x & 0 & -f_x P_x d \\
f_x & 0 & -f_x (P_x - b) d \\ 0 & f_y & -f_y P_y d \end{bmatrix}, \qquad
\frac{\partial (u_L, u_R, v)}{\partial (f_x, f_y, s, u_0, v_0, b)} = \begin{bmatrix}
P_x d & 0 & 0 & 1 & 0 & 0 \\ (P_x - b) d & 0 & 0 & 1 & 0 & -f_x d \\ 0 & P_y d & 0 & 0 & 1 & 0
\end{bmatrix},$$
chained with $\partial P / \partial \xi = [-I, [P]_\times]$ and $\partial P / \partial X = R^\top$.
No policy for points behind the camera ($P_z \le 0$, where GTSAM throws
`StereoCheiralityException`): the factors (`stereo_factor`) apply it.
"""

import jax
import jax.numpy as jnp
from jax.typing import ArrayLike

from ..groups import SE3
from ._frame import check_camera_inputs, in_camera, in_camera_jacobians

LAYOUT = "Cal3_S2Stereo: fx, fy, s, u0, v0, b"


def _checked(entry, pose, calibration, point):
    return check_camera_inputs(entry, pose, point, (calibration, 6, "calibration", LAYOUT))


def stereo_values(calibration, P):
    """$(u_L, u_R, v)$ of the camera-frame point `P` (no checks)."""
    fx, fy, u0, v0, b = (calibration[..., k] for k in (0, 1, 3, 4, 5))
    d = 1 / P[..., 2]
    x, y = P[..., 0], P[..., 1]
    return jnp.stack([u0 + fx * x * d, u0 + fx * (x - b) * d, v0 + fy * y * d], -1)


def stereo_project(T_world_camera: SE3, calibration: ArrayLike, point: ArrayLike) -> jax.Array:
    r"""$(u_L, u_R, v)$, shape `(*batch, 3)`, of a world point (GTSAM's `StereoCamera::project`;
    module docstring).

    **Arguments:**

    - `T_world_camera`: `SE3`, the left camera to world.
    - `calibration`: `(*batch, 6)` $(f_x, f_y, s, u_0, v_0, b)$.
    - `point`: `(*batch, 3)` world point.

    Written with lieax operations, so `lieax.jacobian` differentiates it; batch shapes broadcast.
    """
    point, calibration = _checked("stereo_project", T_world_camera, calibration, point)
    return stereo_values(calibration, in_camera(T_world_camera, point))


def stereo_project_jacobians(
    T_world_camera: SE3, calibration: ArrayLike, point: ArrayLike
) -> tuple[jax.Array, jax.Array, jax.Array, jax.Array]:
    r"""`(uvv, J_pose, J_point, J_calibration)` in closed form, shapes `(*batch, 3)`,
    `(*batch, 3, 6)` (tangent $(v, \omega)$, right perturbation), `(*batch, 3, 3)` and
    `(*batch, 3, 6)` (module docstring). Arguments as `stereo_project`."""
    point, calibration = _checked("stereo_project_jacobians", T_world_camera, calibration, point)
    P, J_P_pose, J_P_point = in_camera_jacobians(T_world_camera, point)
    batch = jnp.broadcast_shapes(P.shape[:-1], calibration.shape[:-1])
    calibration = jnp.broadcast_to(calibration, (*batch, 6))
    P = jnp.broadcast_to(P, (*batch, 3))
    fx, fy, b = calibration[..., 0], calibration[..., 1], calibration[..., 5]
    d = 1 / P[..., 2]
    x, y = P[..., 0], P[..., 1]
    zero, one = jnp.zeros_like(d), jnp.ones_like(d)
    J_uvv_P = d[..., None, None] * jnp.stack(
        [
            jnp.stack([fx, zero, -fx * x * d], -1),
            jnp.stack([fx, zero, -fx * (x - b) * d], -1),
            jnp.stack([zero, fy, -fy * y * d], -1),
        ],
        -2,
    )
    J_calibration = jnp.stack(
        [
            jnp.stack([x * d, zero, zero, one, zero, zero], -1),
            jnp.stack([(x - b) * d, zero, zero, one, zero, -fx * d], -1),
            jnp.stack([zero, y * d, zero, zero, one, zero], -1),
        ],
        -2,
    )
    return (
        stereo_values(calibration, P),
        J_uvv_P @ J_P_pose,
        J_uvv_P @ J_P_point,
        J_calibration,
    )
