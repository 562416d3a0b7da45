r"""SE_2(3), extended poses (the states of inertial navigation), stored as
`(w, x, y, z, px, py, pz, vx, vy, vz)`: a unit quaternion (wxyz), a position and a velocity,
$X = [R, p, v;\ 0, 1, 0;\ 0, 0, 1]$ (5×5).

Tangent $\xi = (\rho_p, \omega, \rho_v)$, shape `(*batch, 9)`: position, rotation, velocity, so
that the first six coordinates are SE3's $(v, \omega)$ and the first seven parameters are SE3's
(`pose()`); the order and the matrix layout are manif's `SE_2_3`. GTSAM's `NavState` orders its
tangent $(\delta R, \delta p, \delta v)$; `lieax.conventions.se23_tangent_to_gtsam` and
`se23_tangent_from_gtsam` permute. Right perturbation, so $\dot p = R \rho_p$, $\dot v = R \rho_v$,
$\dot q = q \otimes (0, \omega / 2)$.

Local carrier (see `lieax.groups._base`): the 10-vector tangent of the parameter leaf holds
$(\rho, \omega, \rho_p, \rho_v)$, so its first seven entries are SE3's carrier. The rules of
`exp`, `log`, `compose`, `inverse`, `adjoint`, `as_matrix`, `from_matrix` and `normalize` are the
generic ones of `lieax.groups._generic`; this module gives their values and the kernels `ad`,
$J_r$, $J_r^{-1}$, `hat`, `vee`, and the action on points $X x = R x + p$.

Formulas: the group is two copies of SE(3)'s translation sharing one rotation (Barrau and
Bonnabel, "The invariant extended Kalman filter as a stable observer" (2017), Sec. 3; Luo et al.,
"Geometry of the extended special Euclidean group" (2021)): each block of $\mathrm{Exp}$, $J_r$,
$\mathrm{Ad}$ is SE3's (`lieax.groups._se3`) on $(\rho_p, \omega)$ and on $(\rho_v, \omega)$.
"""

import sys

import jax
import jax.numpy as jnp

from .._checks import broadcast_batch, check_last_axis, match_dtype
from .._linalg import (
    cross,
    matvec,
    quat_conjugate,
    quat_multiply,
    quat_rotate,
    quat_to_matrix,
    rotate_back,
    skew,
    unskew,
)
from . import _generic, _rules
from . import _so3 as so3
from ._base import AbstractGroup
from ._se3 import SE3, _coupling
from ._so3 import SO3


def _split(params):
    return params[..., :4], params[..., 4:7], params[..., 7:]


def _join(q, p, v):
    """Parameters from a quaternion, a position and a velocity, broadcasting their batch shapes."""
    batch = jnp.broadcast_shapes(q.shape[:-1], p.shape[:-1], v.shape[:-1])
    parts = [jnp.broadcast_to(a, (*batch, a.shape[-1])) for a in (q, p, v)]
    return jnp.concatenate(parts, axis=-1)


def _blocks(rows):
    return jnp.concatenate([jnp.concatenate(row, axis=-1) for row in rows], axis=-2)


# ---- the carrier ---------------------------------------------------------------------------------


def to_local(params, carrier):
    r"""The local tangent $(\rho_p, \omega, \rho_v)$ held by a carrier $(\rho, \omega, \rho_p, \rho_v)$."""
    return jnp.concatenate([carrier[..., 4:7], carrier[..., 1:4], carrier[..., 7:]], axis=-1)


def from_local(params, xi):
    r"""The carrier $(0, \omega, \rho_p, \rho_v)$ of a local tangent."""
    zero = jnp.zeros_like(xi[..., :1])
    return jnp.concatenate([zero, xi[..., 3:6], xi[..., :3], xi[..., 6:]], axis=-1)


@jax.custom_jvp
def to_parameters(params):
    """The parameters as a raw array (identity on values)."""
    return params


@to_parameters.defjvp
def _to_parameters_jvp(primals, tangents):
    r"""Carrier to raw derivative: $\dot q = q \otimes (\rho, \omega/2)$, $\dot p = R \rho_p$, $\dot v = R \rho_v$."""
    (params,), (carrier,) = primals, tangents
    raw = to_parameters(params)
    rotation = so3.unit_rotation(raw[..., :4])
    q_dot = so3.quaternion_derivative(raw[..., :4], carrier[..., :4])
    moved = [matvec(rotation, carrier[..., 4:7]), matvec(rotation, carrier[..., 7:])]
    return raw, jnp.concatenate([q_dot, *moved], axis=-1)


@jax.custom_jvp
def from_parameters(params):
    """A raw parameter array as SE23 parameters (identity on values)."""
    return params


@from_parameters.defjvp
def _from_parameters_jvp(primals, tangents):
    r"""Raw derivative to carrier: $(\rho, \omega)$ as in SO3, $\rho_p = R^\top \dot p$, $\rho_v = R^\top \dot v$."""
    (params,), (raw,) = primals, tangents
    rotation = so3.unit_rotation(params[..., :4])
    rotational = so3.radial_and_local(params[..., :4], raw[..., :4])
    moved = [rotate_back(rotation, raw[..., 4:7]), rotate_back(rotation, raw[..., 7:])]
    return from_parameters(params), jnp.concatenate([rotational, *moved], axis=-1)


# ---- the kernels of the generic rules -------------------------------------------------------------


def ad(xi):
    r"""$\mathrm{ad}_\xi = [[\omega]_\times, [\rho_p]_\times, 0;\ 0, [\omega]_\times, 0;\ 0, [\rho_v]_\times, [\omega]_\times]$."""
    w, zero = skew(xi[..., 3:6]), jnp.zeros_like(skew(xi[..., 3:6]))
    return _blocks([[w, skew(xi[..., :3]), zero], [zero, w, zero], [zero, skew(xi[..., 6:]), w]])


def right_jacobian(xi):
    r"""$J_r = [J, Q_p, 0;\ 0, J, 0;\ 0, Q_v, J]$, $J = J_r(\omega)$, $Q_p = Q(-\rho_p, -\omega)$ and
    $Q_v = Q(-\rho_v, -\omega)$ (Barfoot's coupling block, as SE3's $J_r$)."""
    omega, jr = xi[..., 3:6], so3.right_jacobian(xi[..., 3:6])
    zero = jnp.zeros_like(jr)
    coupling_p, coupling_v = _coupling(-xi[..., :3], -omega), _coupling(-xi[..., 6:], -omega)
    return _blocks([[jr, coupling_p, zero], [zero, jr, zero], [zero, coupling_v, jr]])


def right_jacobian_inverse(xi):
    r"""$J_r^{-1} = [J^{-1}, -J^{-1} Q_p J^{-1}, 0;\ 0, J^{-1}, 0;\ 0, -J^{-1} Q_v J^{-1}, J^{-1}]$."""
    omega, inverse_ = xi[..., 3:6], so3.right_jacobian_inverse(xi[..., 3:6])
    zero = jnp.zeros_like(inverse_)
    coupling_p = -inverse_ @ _coupling(-xi[..., :3], -omega) @ inverse_
    coupling_v = -inverse_ @ _coupling(-xi[..., 6:], -omega) @ inverse_
    return _blocks(
        [[inverse_, coupling_p, zero], [zero, inverse_, zero], [zero, coupling_v, inverse_]]
    )


def hat(xi):
    r"""$\xi^\wedge = [[\omega]_\times, \rho_p, \rho_v;\ 0, 0, 0;\ 0, 0, 0]$."""
    top = jnp.concatenate([skew(xi[..., 3:6]), xi[..., :3, None], xi[..., 6:, None]], axis=-1)
    return jnp.concatenate([top, jnp.zeros_like(top[..., :2, :])], axis=-2)


def vee(matrix):
    return jnp.concatenate(
        [matrix[..., :3, 3], unskew(matrix[..., :3, :3]), matrix[..., :3, 4]], -1
    )


# ---- values of the generic operations -------------------------------------------------------------


def _exp(xi):
    r"""$(\mathrm{Exp}(\omega),\ J_l(\omega)\rho_p,\ J_l(\omega)\rho_v)$ with $J_l(\omega) = J_r(-\omega)$."""
    omega = xi[..., 3:6]
    moved = [
        so3.apply_right_jacobian(-omega, xi[..., :3]),
        so3.apply_right_jacobian(-omega, xi[..., 6:]),
    ]
    return jnp.concatenate([so3.exp(omega), *moved], axis=-1)


def _log(params):
    r"""$(J_l^{-1}(\omega) p,\ \omega,\ J_l^{-1}(\omega) v)$, $\omega = \mathrm{Log}(q)$."""
    q, p, v = _split(params)
    omega = so3.log(q)
    moved = [so3.apply_right_jacobian_inverse(-omega, t) for t in (p, v)]
    return jnp.concatenate([moved[0], omega, moved[1]], axis=-1)


def _compose(params1, params2):
    r"""$(q_1 \otimes q_2,\ p_1 + R_1 p_2,\ v_1 + R_1 v_2)$."""
    (q1, p1, v1), (q2, p2, v2) = _split(params1), _split(params2)
    return _join(quat_multiply(q1, q2), quat_rotate(q1, p2) + p1, quat_rotate(q1, v2) + v1)


def _inverse(params):
    r"""$(\bar q,\ -R^\top p,\ -R^\top v)$."""
    q, p, v = _split(params)
    q_inverse = quat_conjugate(q)
    return _join(q_inverse, -quat_rotate(q_inverse, p), -quat_rotate(q_inverse, v))


def _adjoint(params):
    r"""$\mathrm{Ad}_X = [R, [p]_\times R, 0;\ 0, R, 0;\ 0, [v]_\times R, R]$."""
    q, p, v = _split(params)
    rotation = quat_to_matrix(q)
    zero = jnp.zeros_like(rotation)
    rows = [
        [rotation, skew(p) @ rotation, zero],
        [zero, rotation, zero],
        [zero, skew(v) @ rotation, rotation],
    ]
    return _blocks(rows)


def _as_matrix(params):
    r"""$[R, p, v;\ 0, 1, 0;\ 0, 0, 1]$."""
    q, p, v = _split(params)
    top = jnp.concatenate([quat_to_matrix(q), p[..., None], v[..., None]], axis=-1)
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


@jax.custom_jvp
def act(params, points):
    """$X x = R x + p$ (the pose part acts; the velocity does not move points)."""
    return matvec(quat_to_matrix(params[..., :4]), points) + params[..., 4:7]


@_rules.defjvp(act)
def _act_jvp(primals, tangents):
    r"""$\dot y = R(\rho_p + \omega \times x + \dot x)$, as SE3's action."""
    (params, points), (carrier, points_dot) = primals, tangents
    moved = act(params, points)
    direction = _rules.add(
        None if _rules.is_zero(carrier) else carrier[..., 4:7] + cross(carrier[..., 1:4], points),
        None if _rules.is_zero(points_dot) else points_dot,
    )
    if direction is None:
        return _rules.finish(moved, None)
    return _rules.finish(moved, matvec(so3.as_matrix(params[..., :4]), direction))


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
    def from_pose_and_velocity(cls, pose: SE3, velocity):
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
