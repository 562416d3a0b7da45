r"""SO(2), rotations in the plane, stored as unit complex numbers $(\cos\theta, \sin\theta)$.

Tangent $\theta \in \mathbb{R}^1$, right perturbation $X \oplus \theta = X\,\mathrm{Exp}(\theta)$.
The derivative of the parameters along a right-local tangent is
$(\dot c, \dot s) = \dot\theta\,(-s, c)$, and back $\dot\theta = c\,\dot s - s\,\dot c$: every
kernel's rule converts the incoming parameter tangents to local tangents once, applies the
closed-form block, and converts the result back, so code that touches $(\cos, \sin)$ itself still
gets correct derivatives. SO(2) is commutative: its adjoint and Jacobians of Exp are $[1]$.

Formulas: Solà, Deray, Atchuthan, "A micro Lie theory for state estimation in robotics" (2018),
App. A; the coefficients are the $g_n$ of `lieax.groups._series`.
"""

import jax
import jax.numpy as jnp

from .._checks import as_float_array
from . import _rules
from ._base import AbstractGroup
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
    r"""$R^\top p = c\,p - s\,J p$."""
    return cs[..., :1] * p - cs[..., 1:] * perp(p)


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
    return to_local(cs, rotation_part(m_dot)) / norm


def to_local(cs, cs_dot):
    r"""$\dot\theta = c\,\dot s - s\,\dot c = (J\,(c, s)) \cdot (\dot c, \dot s)$, shape `(*batch, 1)`."""
    return dot(perp(cs), cs_dot)[..., None]


def from_local(cs, theta):
    r"""$(\dot c, \dot s) = \dot\theta\,(-s, c) = \dot\theta\,J\,(c, s)$."""
    return theta * perp(cs)


# ---- kernels with closed-form rules -------------------------------------------------------------


@jax.custom_jvp
def exp(theta):
    r"""$\mathrm{Exp}(\theta) = (\cos\theta, \sin\theta) = (g_0(s),\ \theta\,g_1(s))$, $s = \theta^2$
    (Solà App. A)."""
    s = theta * theta
    return jnp.concatenate([g(0, s), theta * g(1, s)], axis=-1)


@exp.defjvp
def _exp_jvp(primals, tangents):
    """Local block: $J_r = 1$."""
    (theta,), (theta_dot,) = primals, tangents
    cs = exp(theta)
    return cs, from_local(cs, theta_dot)


@jax.custom_jvp
def log(cs):
    r"""$\mathrm{Log}(c, s) = \mathrm{atan2}(s, c) \in (-\pi, \pi]$ (Solà App. A)."""
    return jnp.arctan2(cs[..., 1:], cs[..., :1])


@log.defjvp
def _log_jvp(primals, tangents):
    """Local block: $J_r^{-1} = 1$."""
    (cs,), (cs_dot,) = primals, tangents
    return log(cs), to_local(cs, cs_dot)


@jax.custom_jvp
def compose(cs1, cs2):
    r"""$R_1 R_2$: the complex product $(c_1 c_2 - s_1 s_2,\ s_1 c_2 + c_1 s_2)$."""
    return rotate(cs1, cs2)


@_rules.defjvp(compose)
def _compose_jvp(primals, tangents):
    r"""Local block: $\dot\theta = \dot\theta_1 + \dot\theta_2$ (Solà App. A: SO(2) is commutative)."""
    (cs1, cs2), (cs1_dot, cs2_dot) = primals, tangents
    cs = compose(cs1, cs2)
    theta = _rules.add(
        _rules.local_tangent(to_local, cs1, cs1_dot), _rules.local_tangent(to_local, cs2, cs2_dot)
    )
    return _rules.finish(cs, None if theta is None else from_local(cs, theta))


@jax.custom_jvp
def inverse(cs):
    r"""$R^\top = (c, -s)$."""
    return cs * jnp.array([1.0, -1.0], dtype=cs.dtype)


@inverse.defjvp
def _inverse_jvp(primals, tangents):
    r"""Local block: $\dot\theta_{out} = -\dot\theta$ (Solà App. A)."""
    (cs,), (cs_dot,) = primals, tangents
    cs_inv = inverse(cs)
    return cs_inv, from_local(cs_inv, -to_local(cs, cs_dot))


@jax.custom_jvp
def act(cs, points):
    r"""$R\,p$."""
    return rotate(cs, points)


@_rules.defjvp(act)
def _act_jvp(primals, tangents):
    r"""$\dot y = R(\dot\theta\,J p + \dot p)$: blocks $R J p$ and $R$ (Solà App. A)."""
    (cs, points), (cs_dot, points_dot) = primals, tangents
    moved = act(cs, points)
    theta = _rules.local_tangent(to_local, cs, cs_dot)
    direction = _rules.add(
        None if theta is None else theta * perp(points),
        None if _rules.is_zero(points_dot) else points_dot,
    )
    return _rules.finish(moved, None if direction is None else rotate(cs, direction))


def adjoint(cs):
    r"""$\mathrm{Ad} = [1]$ (Solà App. A), shape `(*batch, 1, 1)`."""
    return jnp.ones_like(cs[..., :1, None])


@jax.custom_jvp
def as_matrix(cs):
    """$R = [[c, -s], [s, c]]$."""
    return rotation_matrix(cs)


@as_matrix.defjvp
def _as_matrix_jvp(primals, tangents):
    r"""$\dot R = R\,\mathrm{hat}(\dot\theta) = \dot\theta\,R J$."""
    (cs,), (cs_dot,) = primals, tangents
    rotation = as_matrix(cs)
    return rotation, rotation @ hat(to_local(cs, cs_dot))


@jax.custom_jvp
def from_matrix(rotation):
    r"""The nearest rotation: $(c, s)$ along $(m_{00} + m_{11},\ m_{10} - m_{01})$ (exact for a
    rotation matrix; the identity for a reflection, where no rotation is nearest)."""
    cs, _ = nearest_rotation(rotation)
    return cs


@from_matrix.defjvp
def _from_matrix_jvp(primals, tangents):
    r"""$\dot\theta$ of `nearest_rotation_tangent` (the skew part of $R^\top \dot R$ at a rotation)."""
    (rotation,), (rotation_dot,) = primals, tangents
    cs, norm = nearest_rotation(rotation)
    return cs, from_local(cs, nearest_rotation_tangent(cs, norm, rotation_dot))


def normalize(cs):
    return cs / jnp.linalg.norm(cs, axis=-1, keepdims=True)


def hat(theta):
    r"""$\mathrm{hat}(\theta) = \theta J = [[0, -\theta], [\theta, 0]]$."""
    zero = jnp.zeros_like(theta[..., 0])
    t = theta[..., 0]
    return jnp.stack([jnp.stack([zero, -t], axis=-1), jnp.stack([t, zero], axis=-1)], axis=-2)


def vee(matrix):
    r"""$\theta$ of the skew part of `matrix`: $(m_{10} - m_{01}) / 2$."""
    return 0.5 * (matrix[..., 1, 0] - matrix[..., 0, 1])[..., None]


def right_jacobian(theta):
    """$J_r = [1]$ (Solà App. A), shape `(*batch, 1, 1)`."""
    return jnp.ones_like(theta[..., None])


right_jacobian_inverse = right_jacobian  # [1] as well


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

    @classmethod
    def from_angle(cls, theta):
        """From angles of shape `(*batch,)` (radians, counter-clockwise)."""
        theta = as_float_array(theta, "SO2.from_angle theta")
        return cls._wrap(exp(theta[..., None]))

    def as_angle(self) -> jax.Array:
        r"""The angle in $(-\pi, \pi]$, shape `(*batch,)` (`log()` without its last axis)."""
        return log(self._params)[..., 0]
