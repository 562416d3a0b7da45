r"""Bearings: the unit direction of a world point in the camera (or body) frame, an `S2`, and
its error against a measured bearing in S2's tangent, with closed-form Jacobians.

The bearing of $X$ seen from $T_{wc}$ is $q = P / |P|$, $P = T_{wc}^{-1} X$ (`_frame`; GTSAM's
`Pose3::bearing(Point3)`). Its error against a measured unit bearing $m$ is the logarithm of S2
at $m$ in lieax's tangent basis $B_m$ (`lieax.S2.basis`):
$$e(q) = \frac{\theta}{\sin\theta} B_m^\top q, \qquad \theta = \mathrm{atan2}(|m \times q|,
m^\top q), \qquad |e| = \theta,$$
the geodesic angle (GTSAM's `Unit3::localCoordinates(m, q)`, the error of its
`BearingFactor<Pose3, Point3>`, in GTSAM's basis; both bases span the tangent plane, so the
norms, and the costs, agree). The error grows with the angle up to $\pi$, so the mirrored
point ($q = -m$) is a maximum of the cost, not a minimum, and a bearing needs no cheirality
policy; at exactly $q = -m$, where the direction is undefined, $e$ is set to $(\pi, 0)$ with
a zero Jacobian. With $c = m^\top q$, $s = \sin\theta$, $f(c) = \theta / s$ and
$f'(c) = (\theta c - s) / s^3$ (series $1 + \theta^2/6 + 7\theta^4/360 + 31\theta^6/15120$
and $-(1/3 + 2\theta^2/15 + 2\theta^4/63)$ below a dtype-dependent angle):
$$\frac{\partial e}{\partial q} = f B_m^\top + f'(c)\,(B_m^\top q)\, m^\top, \qquad
\frac{\partial q}{\partial P} = \frac{I - q q^\top}{|P|},$$
chained with $\partial P / \partial \xi = [-I, [P]_\times]$ and $\partial P / \partial X = R^\top$.
"""

import jax
import jax.numpy as jnp
from jax.typing import ArrayLike

from .._linalg import dot
from ..groups import S2, SE3, kernels
from ._frame import check_camera_inputs, in_camera, in_camera_jacobians

# below this angle θ/sin θ and its derivative use their series (the closed form loses
# ~eps/θ² relative to cancellation; the series' first dropped term is ~θ⁶/100)
_SERIES_ANGLE = {jnp.dtype("float64"): 1e-2}  # float32 and narrower: 0.2


def _checked(entry, pose, point, measured=None):
    if isinstance(measured, S2):
        measured = measured.unit_vector()
    extra = [] if measured is None else [(measured, 3, "measured", "unit bearing")]
    return check_camera_inputs(entry, pose, point, *extra)


def _broadcast(a, b):
    batch = jnp.broadcast_shapes(a.shape[:-1], b.shape[:-1])
    return jnp.broadcast_to(a, (*batch, a.shape[-1])), jnp.broadcast_to(b, (*batch, b.shape[-1]))


def bearing(T_world_camera: SE3, point: ArrayLike) -> S2:
    r"""The `S2` bearing $q = P / |P|$ of world points in the camera frame (GTSAM's
    `Pose3::bearing`); undefined at the camera's centre."""
    (point,) = _checked("bearing", T_world_camera, point)
    P = in_camera(T_world_camera, point)
    return S2(P / jnp.sqrt(dot(P, P))[..., None])


def _angle_factor(m, q, projected):
    r"""`(f, f', θ, antipodal)` of $f = θ / \sin θ$ at $c = m^T q$ (module docstring), with the
    series branch below `_SERIES_ANGLE` and a finite stand-in at the antipode. $\sin θ$ is
    $|B_m^T q|$ (equal on the sphere), so that $|e| = θ$ to rounding even next to the antipode,
    where both are tiny."""
    c = dot(m, q)
    sine_squared = dot(projected, projected)
    antipodal = (sine_squared == 0) & (c < 0)
    sine = jnp.sqrt(jnp.where(sine_squared > 0, sine_squared, 1.0))
    sine = jnp.where(sine_squared > 0, sine, 0.0)
    theta = jnp.arctan2(sine, c)
    small = theta < _SERIES_ANGLE.get(jnp.dtype(q.dtype), 0.2)
    safe_sine = jnp.where(small | antipodal, 1.0, sine)
    safe_theta = jnp.where(small | antipodal, 1.0, theta)
    t2 = theta * theta
    f_series = 1 + t2 * (1 / 6 + t2 * (7 / 360 + t2 * 31 / 15120))
    df_series = -(1 / 3 + t2 * (2 / 15 + t2 * 2 / 63))
    f = jnp.where(small, f_series, safe_theta / safe_sine)
    df = jnp.where(small, df_series, (safe_theta * c - safe_sine) / safe_sine**3)
    return f, df, theta, antipodal


def _error_values(m, q):
    basis_m = kernels.s2_basis(m)
    projected = jnp.einsum("...ij,...i->...j", basis_m, q)
    f, df, _, antipodal = _angle_factor(m, q, projected)
    stand_in = jnp.stack([jnp.pi * jnp.ones_like(f), jnp.zeros_like(f)], -1)
    error = jnp.where(antipodal[..., None], stand_in, f[..., None] * projected)
    return error, basis_m, projected, f, df, antipodal


def bearing_error(T_world_camera: SE3, point: ArrayLike, measured: S2 | ArrayLike) -> jax.Array:
    r"""$e = \frac{\theta}{\sin\theta} B_m^\top q$, shape `(*batch, 2)`: the error of the bearing
    $q$ of `point` seen from `T_world_camera` against `measured` (an `S2` or unit vectors
    `(*batch, 3)`), in S2's tangent at $m$, $|e|$ the angle between them (module docstring).
    Written with lieax operations, so `lieax.jacobian` differentiates it."""
    point, m = _checked("bearing_error", T_world_camera, point, measured)
    P = in_camera(T_world_camera, point)
    m, q = _broadcast(m, P / jnp.sqrt(dot(P, P))[..., None])
    return _error_values(m, q)[0]


def bearing_error_jacobians(
    T_world_camera: SE3, point: ArrayLike, measured: S2 | ArrayLike
) -> tuple[jax.Array, jax.Array, jax.Array]:
    r"""`(error, J_error_pose, J_error_point)` in closed form, shapes `(*batch, 2)`,
    `(*batch, 2, 6)` (tangent $(v, \omega)$, right perturbation) and `(*batch, 2, 3)` (module
    docstring). Arguments as `bearing_error`."""
    point, m = _checked("bearing_error_jacobians", T_world_camera, point, measured)
    P, J_P_pose, J_P_point = in_camera_jacobians(T_world_camera, point)
    P, m = _broadcast(P, m)
    norm = jnp.sqrt(dot(P, P))
    q = P / norm[..., None]
    error, basis_m, projected, f, df, antipodal = _error_values(m, q)
    J_error_q = f[..., None, None] * jnp.swapaxes(basis_m, -1, -2) + (
        df[..., None, None] * projected[..., :, None] * m[..., None, :]
    )
    eye = jnp.eye(3, dtype=q.dtype)
    J_q_P = (eye - q[..., :, None] * q[..., None, :]) / norm[..., None, None]
    J_error_P = jnp.where(antipodal[..., None, None], 0.0, J_error_q @ J_q_P)
    return error, J_error_P @ J_P_pose, J_error_P @ J_P_point
