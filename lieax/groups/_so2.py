r"""SO(2), rotations in the plane, stored as unit complex numbers $z = (\cos\theta, \sin\theta)$.

Tangent $\theta \in \mathbb{R}^1$, right perturbation $X \oplus \theta = X\,\mathrm{Exp}(\theta)$.

Tangent carrier (the local carrier of `lieax.groups._base`, as SO3's): the 2-vector tangent of
the parameter leaf holds $(\rho, \theta)$ with $\dot z = z\,(\rho + i\theta)$ ($\rho$ the radial
part, zero on the circle), so kernels read and write $\theta$ directly; `SO2(cs)` and
`parameters()` convert to and from the raw derivative, $(\rho, \theta) = \bar z \dot z / |z|^2$.
SO(2) is commutative: its adjoint and Jacobians of Exp are $[1]$, $\mathrm{ad} = [0]$, so every
rule but `act`'s, `from_matrix`'s and `relative_bearing`'s is the generic one of
`lieax.groups._generic`.

Formulas: Solà, Deray, Atchuthan, "A micro Lie theory for state estimation in robotics" (2018),
App. A; the coefficients are the $g_n$ of `lieax.groups._series`.
"""

import sys
from typing import Self

import jax
import jax.numpy as jnp
import numpy as np
from jax.typing import ArrayLike

from .._checks import as_float_array, check_last_axis, is_concrete, to_device
from . import _generic, _host, _rules
from ._base import AbstractGroup
from ._bearing_range import unit_and_length
from ._series import g

# ---- planar algebra on the last axis ------------------------------------------------------------


def perp(p):
    r"""$J p = (-p_y, p_x)$, the rotation by $+\pi/2$, with $J = [[0, -1], [1, 0]] = \mathrm{hat}(1)$."""
    return jnp.stack([-p[..., 1], p[..., 0]], axis=-1)


def dot(a, b):
    return jnp.sum(a * b, axis=-1)


def rotate(cs, p):
    r"""$R\,p = c\,p + s\,J p$ for $R = R(c, s)$; also the complex product $(c + is)(p_x + ip_y)$."""
    return cs[..., :1] * p + cs[..., 1:] * perp(p)


def unrotate(cs, p):
    r"""$R^\top p = c\,p - s\,J p$; also the complex product $(c - is)(p_x + ip_y)$."""
    return cs[..., :1] * p - cs[..., 1:] * perp(p)


def unit(cs):
    r"""$z / |z|$ by plain array operations (the carrier maps read raw parameters)."""
    return cs / jnp.sqrt(dot(cs, cs))[..., None]


def rotation_matrix(cs):
    """$R = [[c, -s], [s, c]]$."""
    c, s = cs[..., 0], cs[..., 1]
    return jnp.stack([jnp.stack([c, -s], axis=-1), jnp.stack([s, c], axis=-1)], axis=-2)


def rotation_part(m):
    r"""$(m_{00} + m_{11},\ m_{10} - m_{01})$: its direction is the $(c, s)$ maximizing
    $\mathrm{tr}(R^\top m)$, the rotation nearest to the 2×2 matrix $m$ in the Frobenius norm."""
    return jnp.stack([m[..., 0, 0] + m[..., 1, 1], m[..., 1, 0] - m[..., 0, 1]], axis=-1)


def nearest_rotation(m):
    """$(c, s)$ of the rotation nearest to the 2×2 matrix $m$, and the norm of `rotation_part(m)`
    (1 where that part is zero, a reflection, where the identity is returned)."""
    part = rotation_part(m)
    norm = jnp.linalg.norm(part, axis=-1, keepdims=True)
    degenerate = norm == 0
    part = jnp.where(degenerate, jnp.array([1.0, 0.0], dtype=part.dtype), part)
    norm = jnp.where(degenerate, 1.0, norm)
    return part / norm, norm


def nearest_rotation_tangent(cs, norm, m_dot):
    r"""The local derivative of `nearest_rotation`: with $(a, b)$ = `rotation_part(m)`,
    $\theta = \mathrm{atan2}(b, a)$ gives $\dot\theta = (c\,\dot b - s\,\dot a) / |(a, b)|$
    (for a rotation matrix, the skew part of $R^\top \dot R$)."""
    return dot(perp(cs), rotation_part(m_dot))[..., None] / norm


# ---- the carrier ---------------------------------------------------------------------------------


def to_local(cs, carrier):
    r"""The right-local tangent $\theta$ held by a carrier $(\rho, \theta)$."""
    return carrier[..., 1:]


def from_local(cs, theta):
    r"""The carrier $(0, \theta)$ of a right-local tangent."""
    return jnp.concatenate([jnp.zeros_like(theta), theta], axis=-1)


def raw_from_carrier(cs, carrier):
    r"""The raw derivative $\dot z = z\,(\rho + i\theta)$ of a carrier."""
    return rotate(cs, carrier)


def carrier_from_raw(cs, cs_dot):
    r"""The carrier $(\rho, \theta) = \bar z \dot z / |z|^2$ of a raw derivative."""
    return unrotate(cs, cs_dot) / dot(cs, cs)[..., None]


# ---- kernels: values (the generic rules of `lieax.groups._generic`) and the action --------------


def _exp(theta):
    r"""$\mathrm{Exp}(\theta) = (\cos\theta, \sin\theta) = (g_0(s),\ \theta\,g_1(s))$, $s = \theta^2$
    (Solà App. A)."""
    s = theta * theta
    return jnp.concatenate([g(0, s), theta * g(1, s)], axis=-1)


def _log(cs):
    r"""$\mathrm{Log}(c, s) = \mathrm{atan2}(s, c) \in (-\pi, \pi]$ (Solà App. A)."""
    return jnp.arctan2(cs[..., 1:], cs[..., :1])


def _inverse(cs):
    r"""$R^\top = (c, -s)$."""
    return cs * jnp.array([1.0, -1.0], dtype=cs.dtype)


def _adjoint(cs):
    r"""$\mathrm{Ad} = [1]$ (Solà App. A), shape `(*batch, 1, 1)`."""
    return jnp.ones_like(cs[..., :1, None])


@jax.custom_jvp
def from_matrix(rotation):
    r"""The nearest rotation: $(c, s)$ along $(m_{00} + m_{11},\ m_{10} - m_{01})$ (exact for a
    rotation matrix; the identity for a reflection, where no rotation is nearest)."""
    cs, _ = nearest_rotation(rotation)
    return cs


@from_matrix.defjvp
def _from_matrix_jvp(primals, tangents):
    r"""$\dot\theta$ of `nearest_rotation_tangent`: the derivative of the projection at any matrix
    (the generic rule, the skew part of $R^\top \dot M$, is it only at rotation matrices)."""
    (rotation,), (rotation_dot,) = primals, tangents
    cs, norm = nearest_rotation(rotation)
    return cs, from_local(cs, nearest_rotation_tangent(cs, norm, rotation_dot))


def _normalize(cs):
    return cs / jnp.linalg.norm(cs, axis=-1, keepdims=True)


def hat(theta):
    r"""$\mathrm{hat}(\theta) = \theta J = [[0, -\theta], [\theta, 0]]$."""
    zero = jnp.zeros_like(theta[..., 0])
    t = theta[..., 0]
    return jnp.stack([jnp.stack([zero, -t], axis=-1), jnp.stack([t, zero], axis=-1)], axis=-2)


def vee(matrix):
    r"""$\theta$ of the skew part of `matrix`: $(m_{10} - m_{01}) / 2$."""
    return 0.5 * (matrix[..., 1, 0] - matrix[..., 0, 1])[..., None]


def ad(theta):
    r"""$\mathrm{ad}_\theta = [0]$ (SO(2) is commutative), shape `(*batch, 1, 1)`."""
    return jnp.zeros_like(theta[..., None])


def right_jacobian(theta):
    """$J_r = [1]$ (Solà App. A), shape `(*batch, 1, 1)`."""
    return jnp.ones_like(theta[..., None])


right_jacobian_inverse = right_jacobian  # [1] as well

_ops = _generic.local_rules(
    sys.modules[__name__], exp=_exp, log=_log, compose=rotate, inverse=_inverse,
    adjoint=_adjoint, as_matrix=rotation_matrix, from_matrix=from_matrix, normalize=_normalize,
)  # fmt: skip
exp, log, compose, inverse = _ops.exp, _ops.log, _ops.compose, _ops.inverse
adjoint, as_matrix, normalize = _ops.adjoint, _ops.as_matrix, _ops.normalize
to_parameters, from_parameters = _ops.to_parameters, _ops.from_parameters


@jax.custom_jvp
def act(cs, points):
    r"""$R\,p$."""
    return rotate(cs, points)


@_rules.defjvp(act)
def _act_jvp(primals, tangents):
    r"""$\dot y = R(\dot\theta\,J p + \dot p)$: blocks $R J p$ and $R$ (Solà App. A)."""
    (cs, points), (carrier, points_dot) = primals, tangents
    moved = act(cs, points)
    direction = _rules.add(
        None if _rules.is_zero(carrier) else carrier[..., 1:] * perp(points),
        None if _rules.is_zero(points_dot) else points_dot,
    )
    if direction is None:
        return _rules.finish(moved, None)
    return _rules.finish(moved, rotate(to_parameters(cs), direction))


@jax.custom_jvp
def relative_bearing(d):
    r"""The rotation $(c, s) = d / |d|$ by the angle $\mathrm{atan2}(d_y, d_x)$ of the direction
    of $d$ (GTSAM's `Rot2::relativeBearing`); the identity $(1, 0)$ at $d = 0$ (see
    `lieax.groups._bearing_range`)."""
    return unit_and_length(d)[0]


@relative_bearing.defjvp
def _relative_bearing_jvp(primals, tangents):
    r"""$\dot\theta = (J u)^\top \dot d / |d| = (d_x \dot d_y - d_y \dot d_x) / |d|^2$ (GTSAM's
    Rot2.cpp: $H = (-d_y, d_x) / |d|^2$), written as the carrier $(0, \dot\theta)$; 0 at $d = 0$."""
    (d,), (d_dot,) = primals, tangents
    u, length, nonzero = unit_and_length(d)
    cs = relative_bearing(d)  # through the kernel: its own derivative is a carrier
    theta_dot = jnp.where(nonzero, dot(perp(u), d_dot)[..., None] / length, 0)
    return cs, from_local(cs, theta_dot)


def sample_uniform(key, batch_shape, dtype):
    """Uniform rotations: a normalized standard normal 2-vector."""
    return normalize(jax.random.normal(key, (*batch_shape, 2), dtype=dtype))


class SO2(AbstractGroup):
    r"""Rotations in the plane: parameters `(cos, sin)`, shape `(*batch, 2)`; tangent $\theta$,
    shape `(*batch, 1)`."""

    tangent_dim = 1
    parameters_dim = 2
    space_dim = 2
    matrix_dim = 2
    parameters_layout = "cos, sin"
    _host_exp = staticmethod(_host.so2_exp)
    _host_from_matrix = staticmethod(_host.so2_nearest_rotation)

    @classmethod
    def from_angle(cls, theta: ArrayLike) -> Self:
        """From angles of shape `(*batch,)` (radians, counter-clockwise)."""
        theta = as_float_array(theta, "SO2.from_angle theta")
        if is_concrete(theta):  # no compilation (`lieax.groups._host`)
            return cls._wrap(to_device(_host.so2_exp(np.asarray(theta)[..., None])))
        return cls._wrap(exp(theta[..., None]))

    @classmethod
    def relative_bearing(cls, direction: ArrayLike) -> Self:
        r"""The rotation by the angle $\mathrm{atan2}(d_y, d_x)$ of 2D vectors $d$ of shape
        `(*batch, 2)`: GTSAM's `Rot2::relativeBearing`, the bearing of a point $d$ seen from the
        origin (`SE2.bearing` is it of $X^{-1} p$). The identity where $d = 0$, with a zero
        derivative (never NaN); elsewhere the derivative is $\dot\theta = (d_x \dot d_y -
        d_y \dot d_x) / |d|^2$, also under `jax.grad` of any order."""
        direction = check_last_axis(direction, 2, "SO2.relative_bearing direction", "x, y")
        return cls._wrap(relative_bearing(direction))

    def as_angle(self) -> jax.Array:
        r"""The angle in $(-\pi, \pi]$, shape `(*batch,)` (`log()` without its last axis)."""
        return log(self._params)[..., 0]
