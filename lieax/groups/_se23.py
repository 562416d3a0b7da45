r"""SE_2(3), extended poses (the states of inertial navigation), stored as
`(w, x, y, z, px, py, pz, vx, vy, vz)`: a unit quaternion (wxyz), a position and a velocity,
$X = [R, p, v;\ 0, 1, 0;\ 0, 0, 1]$ (5×5).

Tangent $\xi = (\rho_p, \omega, \rho_v)$, shape `(*batch, 9)`: position, rotation, velocity, so
that the first six coordinates are SE3's $(v, \omega)$ and the first seven parameters are SE3's
(`pose()`); the order and the matrix layout are manif's `SE_2_3`. GTSAM's `NavState` orders its
tangent $(\delta R, \delta p, \delta v)$; `lieax.conventions.se23_tangent_to_gtsam` and
`se23_tangent_from_gtsam` permute. Right perturbation: $\dot p = R \rho_p$, $\dot v = R \rho_v$,
$\dot q = q \otimes (0, \omega / 2)$. The local carrier (`lieax.groups._base`) holds
$(\rho, \omega, \rho_p, \rho_v)$, so its first seven entries are SE3's carrier and the action on
points is SE3's. Every other rule is generic (`lieax.groups._generic`): this module gives values
and the kernels `ad`, $J_r$, $J_r^{-1}$, `hat`, `vee` and the carrier maps.

Formulas: the group is two copies of SE(3)'s translation sharing one rotation (Barrau and
Bonnabel, "The invariant extended Kalman filter as a stable observer" (2017), Sec. 3; Luo et al.,
"Geometry of the extended special Euclidean group" (2021)): each block of $\mathrm{Exp}$, $J_r$,
$\mathrm{Ad}$ is SE3's (`lieax.groups._se3`) on $(\rho_p, \omega)$ and on $(\rho_v, \omega)$.
"""

import sys
from typing import Self

import jax
import jax.numpy as jnp
from jax.typing import ArrayLike

from .._checks import broadcast_batch, check_last_axis, match_dtype
from .._linalg import blocks, matvec, quat_conjugate, quat_multiply, quat_rotate, rotate_back, skew
from . import _generic
from . import _se3 as se3
from . import _so3 as so3
from ._base import AbstractGroup
from ._se3 import SE3, _coupling
from ._so3 import SO3


def _join(q, p, v):
    """Parameters from a quaternion, a position and a velocity, broadcasting their batch shapes."""
    batch = jnp.broadcast_shapes(q.shape[:-1], p.shape[:-1], v.shape[:-1])
    return jnp.concatenate([jnp.broadcast_to(a, (*batch, a.shape[-1])) for a in (q, p, v)], -1)


def to_local(params, carrier):
    r"""The local tangent $(\rho_p, \omega, \rho_v)$ held by a carrier $(\rho, \omega, \rho_p, \rho_v)$."""
    return jnp.concatenate([carrier[..., 4:7], carrier[..., 1:4], carrier[..., 7:]], axis=-1)


def from_local(params, xi):
    r"""The carrier $(0, \omega, \rho_p, \rho_v)$ of a local tangent."""
    zero = jnp.zeros_like(xi[..., :1])
    return jnp.concatenate([zero, xi[..., 3:6], xi[..., :3], xi[..., 6:]], axis=-1)


def raw_from_carrier(params, carrier):
    r"""The raw derivative of a carrier: SE3's, and $\dot v = R \rho_v$."""
    moved = matvec(so3.unit_rotation(params[..., :4]), carrier[..., 7:])
    return jnp.concatenate([se3.raw_from_carrier(params[..., :7], carrier[..., :7]), moved], -1)


def carrier_from_raw(params, raw):
    r"""The carrier of a raw derivative: SE3's, and $\rho_v = R^\top \dot v$."""
    moved = rotate_back(so3.unit_rotation(params[..., :4]), raw[..., 7:])
    return jnp.concatenate([se3.carrier_from_raw(params[..., :7], raw[..., :7]), moved], -1)


def ad(xi):
    r"""$\mathrm{ad}_\xi = [[\omega]_\times, [\rho_p]_\times, 0;\ 0, [\omega]_\times, 0;\ 0, [\rho_v]_\times, [\omega]_\times]$."""
    w, zero = skew(xi[..., 3:6]), jnp.zeros_like(skew(xi[..., 3:6]))
    return blocks([[w, skew(xi[..., :3]), zero], [zero, w, zero], [zero, skew(xi[..., 6:]), w]])


def right_jacobian(xi):
    r"""$J_r = [J, Q_p, 0;\ 0, J, 0;\ 0, Q_v, J]$, $J = J_r(\omega)$, $Q_p = Q(-\rho_p, -\omega)$ and
    $Q_v = Q(-\rho_v, -\omega)$ (Barfoot's coupling block, as SE3's $J_r$)."""
    omega, jr = xi[..., 3:6], so3.right_jacobian(xi[..., 3:6])
    zero = jnp.zeros_like(jr)
    coupling_p, coupling_v = _coupling(-xi[..., :3], -omega), _coupling(-xi[..., 6:], -omega)
    return blocks([[jr, coupling_p, zero], [zero, jr, zero], [zero, coupling_v, jr]])


def right_jacobian_inverse(xi):
    r"""$J_r^{-1} = [J^{-1}, -J^{-1} Q_p J^{-1}, 0;\ 0, J^{-1}, 0;\ 0, -J^{-1} Q_v J^{-1}, J^{-1}]$."""
    omega, inv = xi[..., 3:6], so3.right_jacobian_inverse(xi[..., 3:6])
    zero = jnp.zeros_like(inv)
    coupling_p = -inv @ _coupling(-xi[..., :3], -omega) @ inv
    coupling_v = -inv @ _coupling(-xi[..., 6:], -omega) @ inv
    return blocks([[inv, coupling_p, zero], [zero, inv, zero], [zero, coupling_v, inv]])


def hat(xi):
    r"""$\xi^\wedge = [[\omega]_\times, \rho_p, \rho_v;\ 0, 0, 0;\ 0, 0, 0]$."""
    top = jnp.concatenate([se3.hat(xi[..., :6])[..., :3, :], xi[..., 6:, None]], axis=-1)
    return jnp.concatenate([top, jnp.zeros_like(top[..., :2, :])], axis=-2)


def vee(matrix):
    return jnp.concatenate([se3.vee(matrix[..., :4, :4]), matrix[..., :3, 4]], axis=-1)


# ---- values of the generic operations -------------------------------------------------------------


def _exp(xi):
    r"""$(\mathrm{Exp}_{SE3}(\rho_p, \omega),\ J_l(\omega)\rho_v)$ with $J_l(\omega) = J_r(-\omega)$."""
    velocity = so3.apply_right_jacobian(-xi[..., 3:6], xi[..., 6:])
    return jnp.concatenate([se3._exp(xi[..., :6]), velocity], axis=-1)


def _log(params):
    r"""$(\mathrm{Log}_{SE3}(q, p),\ J_l^{-1}(\omega) v)$, $\omega = \mathrm{Log}(q)$."""
    pose = se3._log(params[..., :7])
    velocity = so3.apply_right_jacobian_inverse(-pose[..., 3:], params[..., 7:])
    return jnp.concatenate([pose, velocity], axis=-1)


def _compose(params1, params2):
    r"""$(q_1 \otimes q_2,\ p_1 + R_1 p_2,\ v_1 + R_1 v_2)$."""
    q1, q2 = params1[..., :4], params2[..., :4]
    moved = [quat_rotate(q1, params2[..., i:j]) + params1[..., i:j] for i, j in ((4, 7), (7, 10))]
    return _join(quat_multiply(q1, q2), *moved)


def _inverse(params):
    r"""$(\bar q,\ -R^\top p,\ -R^\top v)$."""
    q_inverse = quat_conjugate(params[..., :4])
    moved = [-quat_rotate(q_inverse, params[..., i:j]) for i, j in ((4, 7), (7, 10))]
    return _join(q_inverse, *moved)


def _adjoint(params):
    r"""$\mathrm{Ad}_X = [R, [p]_\times R, 0;\ 0, R, 0;\ 0, [v]_\times R, R]$."""
    pose, v = se3._adjoint(params[..., :7]), params[..., 7:]
    rotation, zero = pose[..., :3, :3], jnp.zeros_like(pose[..., :3, :3])
    return blocks([[pose, jnp.zeros_like(pose[..., :3])], [zero, skew(v) @ rotation, rotation]])


def _as_matrix(params):
    r"""$[R, p, v;\ 0, 1, 0;\ 0, 0, 1]$."""
    top = jnp.concatenate([se3._as_matrix(params[..., :7])[..., :3, :], params[..., 7:, None]], -1)
    bottom = jnp.broadcast_to(jnp.eye(5, dtype=params.dtype)[3:], (*top.shape[:-2], 2, 5))
    return jnp.concatenate([top, bottom], axis=-2)


def _from_matrix(matrix):
    """Rotation by `SO3.from_matrix` (re-orthogonalized), position and velocity the last columns."""
    return _join(so3.from_matrix(matrix[..., :3, :3]), matrix[..., :3, 3], matrix[..., :3, 4])


def _normalize(params):
    """Unit quaternion, position and velocity unchanged."""
    return jnp.concatenate([so3.normalize(params[..., :4]), params[..., 4:]], axis=-1)


_ops = _generic.local_rules(
    sys.modules[__name__], exp=_exp, log=_log, compose=_compose, inverse=_inverse,
    adjoint=_adjoint, as_matrix=_as_matrix, from_matrix=_from_matrix, normalize=_normalize,
)  # fmt: skip
exp, log, compose, inverse = _ops.exp, _ops.log, _ops.compose, _ops.inverse
adjoint, as_matrix = _ops.adjoint, _ops.as_matrix
from_matrix, normalize = _ops.from_matrix, _ops.normalize
to_parameters, from_parameters = _ops.to_parameters, _ops.from_parameters


def act(params, points):
    """$X x = R x + p$: SE3's action (and rule) on the pose part; the velocity does not move points."""
    return se3.act(params[..., :7], points)


def sample_uniform(key, batch_shape, dtype):
    """Uniform rotation (Haar), position and velocity uniform in $[-1, 1]^3$."""
    key_rotation, key_rest = jax.random.split(key)
    q = so3.sample_uniform(key_rotation, batch_shape, dtype)
    rest = jax.random.uniform(key_rest, (*batch_shape, 6), dtype=q.dtype, minval=-1.0, maxval=1.0)
    return jnp.concatenate([q, rest], axis=-1)


class SE23(AbstractGroup):
    r"""Extended poses: parameters `(w, x, y, z, px, py, pz, vx, vy, vz)`, shape `(*batch, 10)`;
    tangent $(\rho_p, \omega, \rho_v)$, shape `(*batch, 9)`."""

    tangent_dim = 9
    parameters_dim = 10
    space_dim = 3
    matrix_dim = 5
    parameters_layout = "quaternion wxyz, then position xyz, then velocity xyz"

    @classmethod
    def from_pose_and_velocity(cls, pose: SE3, velocity: ArrayLike) -> Self:
        """$(R, p, v)$ from a pose $(R, p)$ and a velocity in the world frame."""
        name = "SE23.from_pose_and_velocity"
        if not isinstance(pose, SE3):
            raise TypeError(f"pose must be an SE3, got {type(pose).__name__}.")
        velocity = match_dtype(velocity, pose.dtype, f"{name} velocity", "the pose")
        velocity = check_last_axis(velocity, 3, f"{name} velocity")
        broadcast_batch(name, pose.batch_shape, velocity.shape[:-1])
        raw = pose.parameters()
        return cls(_join(raw[..., :4], raw[..., 4:], velocity))

    def pose(self) -> SE3:
        """The pose $(R, p)$ (its carrier is the first seven entries of this one's)."""
        return SE3._wrap(self._params[..., :7])

    def rotation(self) -> SO3:
        return SO3._wrap(self._params[..., :4])

    def position(self) -> jax.Array:
        return self.parameters()[..., 4:7]

    def velocity(self) -> jax.Array:
        return self.parameters()[..., 7:]
