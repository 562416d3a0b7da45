r"""A world point in the camera's frame, and its closed-form Jacobians (shared by the pinhole,
stereo and bearing models).

The camera's pose is $T_{wc} = [R, t]$ (`T_world_camera`, camera to world, as GTSAM's
`PinholeCamera`, `StereoCamera` and `Pose3::transformTo` take it). A world point $X$ is, in the
camera frame,
$$P = T_{wc}^{-1} X = R^\top (X - t).$$
With the right perturbation $T \oplus \xi = T\,\mathrm{Exp}(\xi)$, $\xi = (v, \omega)$ (lieax's
translation-first order), $(T\,\mathrm{Exp}\,\xi)^{-1} X = \mathrm{Exp}(-\xi) P \approx
P - v + [P]_\times \omega$, so
$$\frac{\partial P}{\partial \xi} = \begin{bmatrix} -I & [P]_\times \end{bmatrix}, \qquad
\frac{\partial P}{\partial X} = R^\top$$
(GTSAM's `Pose3::transformTo`, whose pose block is $[\,[P]_\times, -I\,]$ in its $(\omega, v)$
order; Solà et al., "A micro Lie theory", eq. 181-182 for the inverse action).
"""

import jax.numpy as jnp

from .._checks import broadcast_batch, check_last_axis
from ..groups import SE3, SO3


def check_pose(pose, what="T_world_camera"):
    if not isinstance(pose, SE3):
        raise TypeError(f"{what} must be a lieax.SE3 (camera to world), got {type(pose).__name__}.")


def check_camera_inputs(entry, pose, point, *extra):
    """Checks `pose` (an SE3), `point` `(*batch, 3)` and `extra` `(array, size, what, layout)`
    entries, and that the batch shapes broadcast; returns `(point, *arrays)`."""
    check_pose(pose, f"{entry}: T_world_camera")
    point = check_last_axis(point, 3, f"{entry}: point")
    arrays = [
        check_last_axis(x, size, f"{entry}: {what}", layout) for x, size, what, layout in extra
    ]
    broadcast_batch(entry, pose.batch_shape, point.shape[:-1], *(a.shape[:-1] for a in arrays))
    return (point, *arrays)


def in_camera(T_world_camera, point):
    """$P = T_{wc}^{-1} X$ through SE3's closed-form rules (differentiable by `lieax.jacobian`)."""
    return T_world_camera.inverse() @ point


def in_camera_jacobians(T_world_camera, point):
    r"""`(P, J_P_pose, J_P_point)`: $P = R^\top (X - t)$, $[-I, [P]_\times]$ `(*batch, 3, 6)`
    and $R^\top$ `(*batch, 3, 3)` (module docstring)."""
    R = T_world_camera.rotation().as_matrix()
    Rt = jnp.swapaxes(R, -1, -2)
    P = jnp.einsum("...ij,...j->...i", Rt, point - T_world_camera.translation())
    eye = jnp.broadcast_to(jnp.eye(3, dtype=P.dtype), P.shape[:-1] + (3, 3))
    J_P_pose = jnp.concatenate([-eye, SO3.hat(P)], axis=-1)
    return P, J_P_pose, jnp.broadcast_to(Rt, P.shape[:-1] + (3, 3))
