r"""SE(2), rigid motions in the plane, stored as $(\cos\theta, \sin\theta, x, y)$.

Tangent $\xi = (v_x, v_y, \omega)$, translation first; right perturbation
$X \oplus \xi = X\,\mathrm{Exp}(\xi)$, so $\dot t = R v$ and $\dot z = z\,i\omega$.

Tangent carrier (the local carrier of `lieax.groups._base`): the 4-vector tangent of the
parameter leaf holds $(\rho, \omega, v)$, aligned with the parameter slots (SO2's carrier in the
$(c, s)$ slot, the local translation $v$ in the translation slot), so kernels read and write local
tangents without conversion; `SE2(params)`, `parameters()`, `translation()` and the constructors
convert where raw arrays cross the API. Every rule but `act`'s, `from_matrix`'s and
`transform_to`'s (behind `bearing`, with `lieax.groups._so2.relative_bearing`) is the generic one
of `lieax.groups._generic`.

Notation: $J = [[0, -1], [1, 0]]$ (the rotation by $+\pi/2$, `perp`), and the coefficients are the
$g_n(s)$ of `lieax.groups._series` at $s = \omega^2$ ($g_1 = \sin\omega/\omega$,
$g_2 = (1 - \cos\omega)/\omega^2$, $g_3 = (\omega - \sin\omega)/\omega^3$).

Formulas: Solà, Deray, Atchuthan, "A micro Lie theory for state estimation in robotics" (2018),
App. C, rewritten with $J$ and the $g_n$ so that none divides by $\omega$.
"""

import sys
from typing import Self

import jax
import jax.numpy as jnp
import numpy as np
from jax.typing import ArrayLike

from .._checks import (
    broadcast_batch,
    check_last_axis,
    common_float_arrays,
    common_host_arrays,
    is_concrete,
    match_dtype,
    to_device,
)
from . import _generic, _host, _rules
from . import _so2 as so2
from ._base import AbstractGroup
from ._bearing_range import norm, target_points
from ._series import g
from ._so2 import SO2, perp, rotate, unrotate
from ._so3 import jr_inverse_coefficient


def stack_matrix(rows):
    """A `(*batch, n, m)` matrix from a nested list of `(*batch,)` entries."""
    return jnp.stack([jnp.stack(row, axis=-1) for row in rows], axis=-2)


# ---- the carrier ---------------------------------------------------------------------------------


def to_local(params, carrier):
    r"""The local tangent $(v, \omega)$ held by a carrier $(\rho, \omega, v)$."""
    return jnp.concatenate([carrier[..., 2:], carrier[..., 1:2]], axis=-1)


def from_local(params, xi):
    r"""The carrier $(0, \omega, v)$ of a local tangent $(v, \omega)$."""
    return jnp.concatenate([jnp.zeros_like(xi[..., 2:]), xi[..., 2:], xi[..., :2]], axis=-1)


def raw_from_carrier(params, carrier):
    r"""The raw derivative of a carrier: $\dot z = z\,(\rho + i\omega)$, $\dot t = R v$."""
    cs = params[..., :2]
    moved = rotate(so2.unit(cs), carrier[..., 2:])
    return jnp.concatenate([so2.raw_from_carrier(cs, carrier[..., :2]), moved], axis=-1)


def carrier_from_raw(params, params_dot):
    r"""The carrier of a raw derivative: $(\rho, \omega)$ as in SO2, $v = R^\top \dot t$."""
    cs = params[..., :2]
    v = unrotate(so2.unit(cs), params_dot[..., 2:])
    return jnp.concatenate([so2.carrier_from_raw(cs, params_dot[..., :2]), v], axis=-1)


# ---- the kernels of the generic rules -------------------------------------------------------------


def log_coefficient(s):
    r"""$h = g_1 / (2 g_2) = \tfrac\omega2 \cot\tfrac\omega2$ (1 at zero, 0 at $\omega = \pi$), with
    $V^{-1} = h I - \tfrac\omega2 J$ since $\det V = g_1^2 + s g_2^2 = 2 g_2$."""
    return g(1, s) / (2.0 * g(2, s))


def right_jacobian(xi):
    r"""$J_r = [[A, b], [0, 1]]$ with $A = g_1 I - \omega g_2 J$, $b = (\omega g_3 I + g_2 J)\,v$
    (Solà eq. 163: $A = [[g_1, \omega g_2], [-\omega g_2, g_1]]$,
    $b = (\omega g_3 v_x - g_2 v_y,\ g_2 v_x + \omega g_3 v_y)$)."""
    vx, vy, w = xi[..., 0], xi[..., 1], xi[..., 2]
    s = w * w
    g1, g2, g3 = g(1, s), g(2, s), g(3, s)
    zero, one = jnp.zeros_like(w), jnp.ones_like(w)
    return stack_matrix(
        [
            [g1, w * g2, w * g3 * vx - g2 * vy],
            [-w * g2, g1, g2 * vx + w * g3 * vy],
            [zero, zero, one],
        ]
    )


def right_jacobian_inverse(xi):
    r"""$J_r^{-1} = [[A^{-1}, -A^{-1} b], [0, 1]]$ with $A^{-1} = h I + \tfrac\omega2 J$ and
    $-A^{-1} b = (\omega D I - \tfrac12 J)\,v$, where $h$ is `log_coefficient` and
    $D = (g_3 - 2 g_4) / (2 g_2)$ is the coefficient of $J_r^{-1}$ of SO(3) (Solà eq. 144)
    (from eq. 163, using $g_1 + s g_3 = 1$ and $g_1 g_3 - g_2^2 = 2 g_4 - g_3$)."""
    vx, vy, w = xi[..., 0], xi[..., 1], xi[..., 2]
    s = w * w
    h, wd = log_coefficient(s), w * jr_inverse_coefficient(s)
    zero, one = jnp.zeros_like(w), jnp.ones_like(w)
    return stack_matrix(
        [
            [h, -0.5 * w, wd * vx + 0.5 * vy],
            [0.5 * w, h, wd * vy - 0.5 * vx],
            [zero, zero, one],
        ]
    )


def ad(xi):
    r"""$\mathrm{ad}_\xi = [[\omega J, -J v], [0, 0]]$, the derivative of $\mathrm{Ad}_{\mathrm{Exp}(\xi)}$
    at zero."""
    vx, vy, w = xi[..., 0], xi[..., 1], xi[..., 2]
    zero = jnp.zeros_like(w)
    return stack_matrix([[zero, -w, vy], [w, zero, -vx], [zero, zero, zero]])


def hat(xi):
    r"""$\mathrm{hat}(v, \omega) = [[\omega J, v], [0, 0]]$."""
    vx, vy, w = xi[..., 0], xi[..., 1], xi[..., 2]
    zero = jnp.zeros_like(w)
    return stack_matrix([[zero, -w, vx], [w, zero, vy], [zero, zero, zero]])


def vee(matrix):
    r"""$(m_{02},\ m_{12},\ (m_{10} - m_{01}) / 2)$: the inverse of `hat` on the skew part."""
    return jnp.concatenate([matrix[..., :2, 2], so2.vee(matrix[..., :2, :2])], axis=-1)


# ---- values of the generic operations -------------------------------------------------------------


def _exp(xi):
    r"""$\mathrm{Exp}(v, \omega) = (\cos\omega, \sin\omega, V v)$ with $V = g_1 I + \omega g_2 J$
    (Solà App. C)."""
    v, w = xi[..., :2], xi[..., 2:]
    s = w * w
    g1 = g(1, s)
    return jnp.concatenate([g(0, s), w * g1, g1 * v + w * g(2, s) * perp(v)], axis=-1)


def _log(params):
    r"""$\mathrm{Log}(X) = (V^{-1} t, \omega)$ with $\omega = \mathrm{atan2}(s, c) \in (-\pi, \pi]$ and
    $V^{-1} = h I - \tfrac\omega2 J$, $h$ of `log_coefficient` (Solà App. C)."""
    cs, t = params[..., :2], params[..., 2:]
    w = jnp.arctan2(cs[..., 1:], cs[..., :1])
    v = log_coefficient(w * w) * t - 0.5 * w * perp(t)
    return jnp.concatenate([v, w], axis=-1)


def _compose(params1, params2):
    r"""$(R_1 R_2,\ R_1 t_2 + t_1)$."""
    cs1, t1 = params1[..., :2], params1[..., 2:]
    cs2, t2 = params2[..., :2], params2[..., 2:]
    return jnp.concatenate([rotate(cs1, cs2), rotate(cs1, t2) + t1], axis=-1)


def _inverse(params):
    r"""$(R^\top, -R^\top t)$."""
    cs, t = params[..., :2], params[..., 2:]
    return jnp.concatenate([cs * jnp.array([1.0, -1.0], dtype=cs.dtype), -unrotate(cs, t)], -1)


def _adjoint(params):
    r"""$\mathrm{Ad}_X = [[R, -J t], [0, 1]] = [[c, -s, y], [s, c, -x], [0, 0, 1]]$ (Solà App. C)."""
    c, s, x, y = (params[..., i] for i in range(4))
    zero, one = jnp.zeros_like(c), jnp.ones_like(c)
    return stack_matrix([[c, -s, y], [s, c, -x], [zero, zero, one]])


def _as_matrix(params):
    """$T = [[R, t], [0, 1]]$."""
    c, s, x, y = (params[..., i] for i in range(4))
    zero, one = jnp.zeros_like(c), jnp.ones_like(c)
    return stack_matrix([[c, -s, x], [s, c, y], [zero, zero, one]])


@jax.custom_jvp
def from_matrix(matrix):
    """The nearest rotation of the 2×2 block (`lieax.groups._so2.nearest_rotation`) and the last column."""
    cs, _ = so2.nearest_rotation(matrix[..., :2, :2])
    return jnp.concatenate([cs, matrix[..., :2, 2]], axis=-1)


@from_matrix.defjvp
def _from_matrix_jvp(primals, tangents):
    r"""$v = R^\top \dot t$, $\omega$ of `lieax.groups._so2.nearest_rotation_tangent`: the derivative
    of the projection at any matrix (the generic rule is it only on the group)."""
    (matrix,), (matrix_dot,) = primals, tangents
    cs, norm = so2.nearest_rotation(matrix[..., :2, :2])
    params = jnp.concatenate([cs, matrix[..., :2, 2]], axis=-1)
    w = so2.nearest_rotation_tangent(cs, norm, matrix_dot[..., :2, :2])
    v = unrotate(cs, matrix_dot[..., :2, 2])
    return params, from_local(params, jnp.concatenate([v, w], axis=-1))


def _normalize(params):
    """Unit $(c, s)$; the translation as given."""
    return jnp.concatenate([so2.normalize(params[..., :2]), params[..., 2:]], axis=-1)


_ops = _generic.local_rules(
    sys.modules[__name__], exp=_exp, log=_log, compose=_compose, inverse=_inverse,
    adjoint=_adjoint, as_matrix=_as_matrix, from_matrix=from_matrix, normalize=_normalize,
)  # fmt: skip
exp, log, compose, inverse = _ops.exp, _ops.log, _ops.compose, _ops.inverse
adjoint, as_matrix, normalize = _ops.adjoint, _ops.as_matrix, _ops.normalize
to_parameters, from_parameters = _ops.to_parameters, _ops.from_parameters


@jax.custom_jvp
def act(params, points):
    """$R p + t$."""
    return rotate(params[..., :2], points) + params[..., 2:]


@_rules.defjvp(act)
def _act_jvp(primals, tangents):
    r"""$\dot y = R(v + \omega J p + \dot p)$: blocks $[R,\ R J p]$ and $R$ (Solà App. C)."""
    (params, points), (carrier, points_dot) = primals, tangents
    moved = act(params, points)
    direction = _rules.add(
        None if _rules.is_zero(carrier) else carrier[..., 2:] + carrier[..., 1:2] * perp(points),
        None if _rules.is_zero(points_dot) else points_dot,
    )
    if direction is None:
        return _rules.finish(moved, None)
    return _rules.finish(moved, rotate(so2.to_parameters(params[..., :2]), direction))


@jax.custom_jvp
def transform_to(params, points):
    r"""$X^{-1} p = R^\top (p - t)$, the points in the pose's frame (GTSAM's `Pose2::transformTo`)."""
    return unrotate(params[..., :2], points - params[..., 2:])


@_rules.defjvp(transform_to)
def _transform_to_jvp(primals, tangents):
    r"""$\dot d = -(v + \omega J d) + R^\top \dot p$: blocks $[-I,\ -J d]$ and $R^\top$ (GTSAM's
    Pose2.cpp, `transformTo`: $[[-1, 0, d_y], [0, -1, -d_x]]$ and $R^\top$)."""
    (params, points), (carrier, points_dot) = primals, tangents
    local = transform_to(params, points)
    moved = _rules.add(
        None if _rules.is_zero(carrier) else -(carrier[..., 2:] + carrier[..., 1:2] * perp(local)),
        None
        if _rules.is_zero(points_dot)
        else unrotate(so2.to_parameters(params[..., :2]), points_dot),
    )
    return _rules.finish(local, moved)


def join(cs, translation):
    """SE2 parameters from SO2 parameters and a raw translation, broadcasting batch shapes (through
    the carrier maps, so the rotation's carrier and the translation's derivative both convert)."""
    batch = jnp.broadcast_shapes(cs.shape[:-1], translation.shape[:-1])
    parts = [jnp.broadcast_to(so2.to_parameters(cs), (*batch, 2))]
    return from_parameters(
        jnp.concatenate([*parts, jnp.broadcast_to(translation, (*batch, 2))], -1)
    )


def sample_uniform(key, batch_shape, dtype):
    """Uniform rotations (`lieax.groups._so2.sample_uniform`), translations uniform in $[-1, 1]^2$."""
    rotation_key, translation_key = jax.random.split(key)
    cs = so2.sample_uniform(rotation_key, batch_shape, dtype)
    t = jax.random.uniform(translation_key, (*batch_shape, 2), dtype, minval=-1.0, maxval=1.0)
    return jnp.concatenate([cs, t.astype(cs.dtype)], axis=-1)


class SE2(AbstractGroup):
    r"""Rigid motions in the plane: parameters `(cos, sin, x, y)`, shape `(*batch, 4)`; tangent
    $(v_x, v_y, \omega)$, shape `(*batch, 3)`."""

    tangent_dim = 3
    parameters_dim = 4
    space_dim = 2
    matrix_dim = 3
    parameters_layout = "cos, sin, x, y"
    _host_exp = staticmethod(_host.se2_exp)
    _host_from_matrix = staticmethod(
        lambda m: np.concatenate([_host.so2_nearest_rotation(m[..., :2, :2]), m[..., :2, 2]], -1)
    )

    @classmethod
    def from_rotation_and_translation(cls, rotation: SO2, translation: ArrayLike) -> Self:
        """$X = (R, t)$ from an `SO2` and translations of shape `(*batch, 2)`, broadcasting batch
        shapes."""
        if not isinstance(rotation, SO2):
            raise TypeError(
                f"SE2.from_rotation_and_translation needs an SO2 rotation, "
                f"got {type(rotation).__name__}."
            )
        translation = match_dtype(translation, rotation.dtype, "SE2 translation", "the rotation")
        translation = check_last_axis(translation, 2, "SE2 translation", "x, y")
        batch = broadcast_batch(
            "SE2.from_rotation_and_translation", rotation.batch_shape, translation.shape[:-1]
        )
        if is_concrete(rotation, translation):  # no compilation (`lieax.groups._host`)
            parts = (np.asarray(rotation._params), np.asarray(translation))
            return cls._wrap(to_device(_host.join(batch, *parts)))
        return cls._wrap(join(rotation._params, translation))

    @classmethod
    def from_xy_theta(cls, x: ArrayLike, y: ArrayLike, theta: ArrayLike) -> Self:
        """From positions and headings (radians), each of shape `(*batch,)`, broadcast together; the
        dtype is that of the arrays among them (Python and NumPy numbers take it)."""
        if is_concrete(x, y, theta):  # no compilation (`lieax.groups._host`)
            x, y, theta = common_host_arrays("SE2.from_xy_theta", x, y, theta)
            batch = broadcast_batch("SE2.from_xy_theta", x.shape, y.shape, theta.shape)
            x, y, theta = (np.broadcast_to(a, batch) for a in (x, y, theta))
            rotation = _host.so2_exp(theta[..., None])
            return cls._wrap(to_device(_host.join(batch, rotation, np.stack([x, y], axis=-1))))
        x, y, theta = common_float_arrays("SE2.from_xy_theta", x, y, theta)
        batch = broadcast_batch("SE2.from_xy_theta", x.shape, y.shape, theta.shape)
        x, y, theta = (jnp.broadcast_to(a, batch) for a in (x, y, theta))
        return cls._wrap(join(so2.exp(theta[..., None]), jnp.stack([x, y], axis=-1)))

    def as_xy_theta(self) -> jax.Array:
        r"""`(x, y, theta)` on the last axis, theta in $(-\pi, \pi]$; inverse of `from_xy_theta`."""
        return jnp.concatenate([self.translation(), so2.log(self._params[..., :2])], axis=-1)

    def bearing(self, target: Self | ArrayLike) -> SO2:
        r"""The direction of `target` seen from this pose, as an `SO2` (GTSAM's `Pose2::bearing`,
        which returns a `Rot2`): $\mathrm{atan2}(d_y, d_x)$ of $d = X^{-1} p$, for points $p$ of
        shape `(*batch, 2)` or the positions $p = t_Y$ of another `SE2` $Y$, broadcasting batch
        shapes. An `SO2` rather than an angle so that the residual against a measured bearing $Z$
        is `X.bearing(p).rminus(Z)` $= \mathrm{Log}(Z^{-1}\hat Z)$, wrapped into $(-\pi, \pi]$
        (an angle difference is $2\pi$ off across $\pm\pi$); `.as_angle()` gives the angle.

        Jacobians (right-local, rule of `transform_to` then `SO2.relative_bearing`; GTSAM's
        Pose2.cpp): $\partial\theta / \partial X = (d_y, -d_x, -|d|^2) / |d|^2$,
        $\partial\theta / \partial p = (J d)^\top R^\top / |d|^2$, and for a pose target
        $(\partial\theta / \partial p)\,[R_Y, 0]$. At $d = 0$ (the point at the pose's origin):
        the identity (heading along the pose's x axis), derivatives 0."""
        points = target_points(self, target, "bearing", 2)
        return SO2._wrap(so2.relative_bearing(transform_to(self._params, points)))

    def range(self, target: Self | ArrayLike) -> jax.Array:
        r"""The distance $|p - t|$ from this pose to `target`, points of shape `(*batch, 2)` or
        another `SE2`'s position, shape `(*batch,)` (GTSAM's `Pose2::range`). Jacobians
        (right-local): $\partial r / \partial X = (-u^\top R, 0)$, $\partial r / \partial p = u^\top$
        with $u = (p - t) / r$ (and $u^\top R_Y$ on a pose target's translation); at $r = 0$ the
        range is 0 with derivatives 0 (`lieax.groups._bearing_range`)."""
        points = target_points(self, target, "range", 2)
        return norm(points - self.translation())

    def rotation(self) -> SO2:
        """$R$, an `SO2` of the same batch shape."""
        return SO2._wrap(self._params[..., :2])

    def translation(self) -> jax.Array:
        """$t$, shape `(*batch, 2)`."""
        return self.parameters()[..., 2:]
