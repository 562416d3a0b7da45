r"""BAL's camera 9-vectors and Snavely's camera `(T_camera_world, intrinsics)`
(`lieax.cameras` has the camera itself: projection, residual, closed-form Jacobians).

The BAL file stores a camera as 9 numbers: the rotation vector of $R$ (axis times angle, the SO3
tangent, so $R = \mathrm{Exp}(\omega)$), $t$, then $f, k_1, k_2$.
"""

import jax
import jax.numpy as jnp
import numpy as np
from jax.typing import ArrayLike

from .._checks import broadcast_batch, check_last_axis, is_concrete, to_device
from ..cameras._snavely import check_pose as _check_pose
from ..groups import SE3, SO3


def bal_to_camera(cameras: ArrayLike) -> tuple[SE3, jax.Array]:
    r"""`(T_camera_world, intrinsics)` from BAL's camera 9-vectors.

    **Arguments:**

    - `cameras`: `(*batch, 9)`: rotation vector $\omega$, translation $t$, $f$, $k_1$, $k_2$.

    **Returns:** the `SE3` $[\mathrm{Exp}(\omega), t]$ (world to camera) and the `(*batch, 3)`
    intrinsics $(f, k_1, k_2)$.
    """
    cameras = check_last_axis(cameras, 9, "BAL cameras", "rotation vector, t, f, k1, k2")
    if is_concrete(cameras):  # sliced in NumPy: building a problem compiles nothing
        cameras = np.asarray(cameras)
        intrinsics = to_device(cameras[..., 6:])
    else:
        intrinsics = cameras[..., 6:]
    pose = SE3.from_rotation_and_translation(SO3.exp(cameras[..., :3]), cameras[..., 3:6])
    return pose, intrinsics


def camera_to_bal(pose: SE3, intrinsics: ArrayLike) -> np.ndarray | jax.Array:
    r"""BAL's camera 9-vectors `(*batch, 9)` from `(T_camera_world, intrinsics)`: the inverse of
    `bal_to_camera` (rotation vectors with angle in $[0, \pi]$).

    Returns a writable NumPy array (a JAX array under a transformation), the form files and SciPy
    take: `scipy.spatial.transform.Rotation.from_rotvec` refuses the read-only view
    `np.asarray` makes of a JAX array ("buffer source array is read-only")."""
    _check_pose(pose)
    intrinsics = check_last_axis(intrinsics, 3, "intrinsics", "f, k1, k2")
    batch = broadcast_batch("camera_to_bal", pose.batch_shape, intrinsics.shape[:-1])
    rotvec = jnp.broadcast_to(pose.rotation().log(), (*batch, 3))
    translation = jnp.broadcast_to(pose.translation(), (*batch, 3))
    cameras = jnp.concatenate([rotvec, translation, jnp.broadcast_to(intrinsics, (*batch, 3))], -1)
    return cameras if isinstance(cameras, jax.core.Tracer) else np.array(cameras)
