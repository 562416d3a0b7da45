r"""SE(3), rigid motions in 3D, stored as `(w, x, y, z, tx, ty, tz)`: a unit quaternion (wxyz) and
a translation, $T = [R(q), t; 0, 1]$.

Tangent $\xi = (v, \omega)$, translation first; right perturbation $T \oplus \xi = T\,\mathrm{Exp}(\xi)$,
so $\dot t = R v$ and $\dot q = q \otimes (0, \omega/2)$.

Tangent carrier (see `lieax.groups._so3`): the 7-vector tangent of the parameter leaf holds
$(\rho, \omega, v)$, the local tangent itself (and the quaternion's radial part $\rho$), so the
rotation slot carries exactly SO3's carrier and kernels use local tangents without conversion.
`SE3(wxyz_xyz)`, `parameters()`, `translation()` and `from_rotation_and_translation` convert
where raw arrays cross the API.

Formulas: Solà, Deray, Atchuthan, "A micro Lie theory for state estimation in robotics" (2018),
Sec. IV-D and App. D; the coupling block $Q$ of the Jacobians from Barfoot, "State Estimation for
Robotics" (2017), eq. 7.86, with coefficients rewritten as the $g_n$ of `lieax.groups._series`.
"""

import sys
from typing import Literal, Self, overload

import jax
import jax.numpy as jnp
import numpy as np
from jax.typing import ArrayLike

from .._checks import broadcast_batch, check_last_axis, is_concrete, match_dtype, to_device
from .._linalg import (
    cross,
    dot,
    matvec,
    quat_conjugate,
    quat_multiply,
    quat_rotate,
    quat_to_matrix,
    rotate_back,
    skew,
    unskew,
)
from . import _bearing_range as bearing_range
from . import _generic, _host, _procrustes, _rules
from . import _so3 as so3
from ._base import AbstractGroup
from ._s2 import S2
from ._series import g
from ._sim3 import Sim3
from ._so3 import SO3

# ---- parameter and tangent layout ---------------------------------------------------------------


def _split(params):
    return params[..., :4], params[..., 4:]


def _join(q, t):
    """Parameters from a quaternion and a translation, broadcasting their batch shapes."""
    batch = jnp.broadcast_shapes(q.shape[:-1], t.shape[:-1])
    return jnp.concatenate(
        [jnp.broadcast_to(q, (*batch, 4)), jnp.broadcast_to(t, (*batch, 3))], axis=-1
    )


def to_local(params, carrier):
    r"""The local tangent $(v, \omega)$ held by a carrier $(\rho, \omega, v)$."""
    return jnp.concatenate([carrier[..., 4:], carrier[..., 1:4]], axis=-1)


def from_local(params, xi):
    r"""The carrier $(0, \omega, v)$ of a local tangent $(v, \omega)$."""
    return jnp.concatenate([jnp.zeros_like(xi[..., :1]), xi[..., 3:], xi[..., :3]], axis=-1)


def raw_from_carrier(params, carrier):
    r"""The raw derivative of a carrier: $\dot q = q \otimes (\rho, \omega/2)$, $\dot t = R v$."""
    q = params[..., :4]
    q_dot = so3.raw_from_carrier(q, carrier[..., :4])
    return jnp.concatenate([q_dot, matvec(so3.unit_rotation(q), carrier[..., 4:])], axis=-1)


def carrier_from_raw(params, params_dot):
    r"""The carrier of a raw derivative: $(\rho, \omega)$ as in SO3, $v = R^\top \dot t$."""
    q = params[..., :4]
    v = rotate_back(so3.unit_rotation(q), params_dot[..., 4:])
    return jnp.concatenate([so3.carrier_from_raw(q, params_dot[..., :4]), v], axis=-1)


@jax.custom_jvp
def join(q, t):
    """SE3 parameters from SO3 parameters and a raw translation, broadcasting batch shapes."""
    return _join(q, t)


@join.defjvp
def _join_jvp(primals, tangents):
    r"""The rotation's carrier passes through; $v = R^\top \dot t$."""
    (q, t), (q_carrier, t_dot) = primals, tangents
    params = join(q, t)
    v = rotate_back(so3.as_matrix(q), t_dot)
    return params, _join(q_carrier, v)


def _rotation_and_translation(params):
    """$R$ and $t$ for use inside rules (through kernels, so that rules differentiate correctly)."""
    return so3.as_matrix(params[..., :4]), to_parameters(params)[..., 4:]


# ---- Jacobians of Exp ---------------------------------------------------------------------------


def _coupling(v, omega):
    r"""Barfoot's $Q(\rho, \phi)$, the upper-right block of $J_l$ (eq. 7.86), with
    $V = [\rho]_\times$, $W = [\phi]_\times$:
    $Q = \tfrac12 V + g_3 (WV + VW + WVW) + g_4 (WWV + VWW - 3WVW)
    + \tfrac12 (g_4 - 3g_5) (WVWW + WWVW)$."""
    s = dot(omega, omega)[..., None, None]
    V, W = skew(v), skew(omega)
    WV, VW = W @ V, V @ W
    WVW = WV @ W
    g4 = g(4, s)
    return (
        0.5 * V
        + g(3, s) * (WV + VW + WVW)
        + g4 * (W @ WV + VW @ W - 3.0 * WVW)
        + 0.5 * (g4 - 3.0 * g(5, s)) * (WVW @ W + W @ WVW)
    )


def _block_upper_triangular(diagonal, corner):
    top = jnp.concatenate([diagonal, corner], axis=-1)
    bottom = jnp.concatenate([jnp.zeros_like(diagonal), diagonal], axis=-1)
    return jnp.concatenate([top, bottom], axis=-2)


def right_jacobian(xi):
    r"""$J_r(\xi) = J_l(-\xi) = [J_r(\omega), Q(-v, -\omega); 0, J_r(\omega)]$ (Solà eq. 179-180)."""
    v, omega = xi[..., :3], xi[..., 3:]
    return _block_upper_triangular(so3.right_jacobian(omega), _coupling(-v, -omega))


def right_jacobian_inverse(xi):
    r"""$J_r^{-1}(\xi) = [J_r^{-1}, -J_r^{-1} Q J_r^{-1}; 0, J_r^{-1}]$ with $Q = Q(-v, -\omega)$."""
    v, omega = xi[..., :3], xi[..., 3:]
    inverse = so3.right_jacobian_inverse(omega)
    return _block_upper_triangular(inverse, -inverse @ _coupling(-v, -omega) @ inverse)


# ---- kernels with closed-form rules -------------------------------------------------------------


def _exp(xi):
    r"""$\mathrm{Exp}(v, \omega) = (\mathrm{Exp}(\omega),\ J_l(\omega)\,v)$ with
    $J_l(\omega) v = v + g_2\,\omega \times v + g_3\,\omega \times (\omega \times v)$ (Solà eq. 172)."""
    v, omega = xi[..., :3], xi[..., 3:]
    s = dot(omega, omega)[..., None]
    wv = cross(omega, v)
    t = v + g(2, s) * wv + g(3, s) * cross(omega, wv)
    return jnp.concatenate([so3.exp(omega), t], axis=-1)


def _log(params):
    r"""$\mathrm{Log}(T) = (J_l^{-1}(\omega)\,t,\ \omega)$, $\omega = \mathrm{Log}(q)$, with
    $J_l^{-1}(\omega) t = t - \tfrac12 \omega \times t + D(\theta)\,\omega \times (\omega \times t)$."""
    q, t = _split(params)
    omega = so3.log(q)
    s = dot(omega, omega)[..., None]
    wt = cross(omega, t)
    v = t - 0.5 * wt + so3.jr_inverse_coefficient(s) * cross(omega, wt)
    return jnp.concatenate([v, omega], axis=-1)


@jax.custom_jvp
def compose(params1, params2):
    r"""$T_1 T_2 = (q_1 \otimes q_2,\ R_1 t_2 + t_1)$."""
    q1, t1 = _split(params1)
    q2, t2 = _split(params2)
    return _join(quat_multiply(q1, q2), quat_rotate(q1, t2) + t1)


@_rules.defjvp(compose)
def _compose_jvp(primals, tangents):
    r"""Local block: $\xi = \mathrm{Ad}(T_2^{-1})\,\xi_1 + \xi_2$, i.e.
    $v = R_2^\top(v_1 + \omega_1 \times t_2) + v_2$, $\omega = R_2^\top \omega_1 + \omega_2$ (Solà eq. 171)."""
    (params1, params2), (params1_dot, params2_dot) = primals, tangents
    params = compose(params1, params2)
    xi1 = _rules.local_tangent(to_local, params1, params1_dot)
    xi2 = _rules.local_tangent(to_local, params2, params2_dot)
    moved = None
    if xi1 is not None:
        rotation2, t2 = _rotation_and_translation(params2)
        v1, omega1 = xi1[..., :3], xi1[..., 3:]
        moved = jnp.concatenate(
            [rotate_back(rotation2, v1 + cross(omega1, t2)), rotate_back(rotation2, omega1)],
            axis=-1,
        )
    xi = _rules.add(moved, xi2)
    return _rules.finish(params, None if xi is None else from_local(params, xi))


@jax.custom_jvp
def inverse(params):
    r"""$T^{-1} = (\bar q,\ -R^\top t)$."""
    q, t = _split(params)
    q_inverse = quat_conjugate(q)
    return jnp.concatenate([q_inverse, -quat_rotate(q_inverse, t)], axis=-1)


@inverse.defjvp
def _inverse_jvp(primals, tangents):
    r"""Local block $-\mathrm{Ad}(T)$: $\omega' = -R\omega$, $v' = -(R v + t \times R\omega)$ (Solà eq. 176)."""
    (params,), (params_dot,) = primals, tangents
    params_inverse = inverse(params)
    rotation, t = _rotation_and_translation(params)
    xi = to_local(params, params_dot)
    rotated_omega = matvec(rotation, xi[..., 3:])
    xi_out = -jnp.concatenate(
        [matvec(rotation, xi[..., :3]) + cross(t, rotated_omega), rotated_omega], -1
    )
    return params_inverse, from_local(params_inverse, xi_out)


@jax.custom_jvp
def act(params, points):
    """$T p = R p + t$."""
    q, t = _split(params)
    return matvec(quat_to_matrix(q), points) + t


@_rules.defjvp(act)
def _act_jvp(primals, tangents):
    r"""$\dot y = R(v + \omega \times p + \dot p)$: blocks $[R, -R[p]_\times]$ and $R$ (Solà eq. 181-182)."""
    (params, points), (params_dot, points_dot) = primals, tangents
    moved = act(params, points)
    # Read (v, ω) straight from the carrier (ρ, ω, v): no concatenation, so no pads in the transpose.
    direction = _rules.add(
        None
        if _rules.is_zero(params_dot)
        else params_dot[..., 4:] + cross(params_dot[..., 1:4], points),
        None if _rules.is_zero(points_dot) else points_dot,
    )
    if direction is None:
        return _rules.finish(moved, None)
    return _rules.finish(moved, matvec(so3.as_matrix(params[..., :4]), direction))


@jax.custom_jvp
def transform_to(params, points):
    r"""$T^{-1} p = R^\top (p - t)$, the points in the pose's frame (GTSAM's `Pose3::transformTo`)."""
    q, t = _split(params)
    return rotate_back(quat_to_matrix(q), points - t)


@_rules.defjvp(transform_to)
def _transform_to_jvp(primals, tangents):
    r"""$\dot d = -(v + \omega \times d) + R^\top \dot p$: blocks $[-I,\ [d]_\times]$ and $R^\top$
    (GTSAM's Pose3.cpp, `transformTo`, in the order $(\omega, v)$: $[[d]_\times, -I]$)."""
    (params, points), (params_dot, points_dot) = primals, tangents
    local = transform_to(params, points)
    moved = _rules.add(
        None
        if _rules.is_zero(params_dot)
        else -(params_dot[..., 4:] + cross(params_dot[..., 1:4], local)),
        None
        if _rules.is_zero(points_dot)
        else rotate_back(so3.as_matrix(params[..., :4]), points_dot),
    )
    return _rules.finish(local, moved)


def _adjoint(params):
    r"""$\mathrm{Ad}_T = [R, [t]_\times R; 0, R]$ (translation-first tangents; Solà eq. 178)."""
    q, t = _split(params)
    rotation = quat_to_matrix(q)
    return _block_upper_triangular(rotation, skew(t) @ rotation)


def ad(xi):
    r"""$\mathrm{ad}_\xi = [[\omega]_\times, [v]_\times; 0, [\omega]_\times]$, the derivative of $\mathrm{Ad}$."""
    return _block_upper_triangular(skew(xi[..., 3:]), skew(xi[..., :3]))


def hat(xi):
    r"""$\xi^\wedge = [[\omega]_\times, v; 0, 0]$."""
    top = jnp.concatenate([skew(xi[..., 3:]), xi[..., :3, None]], axis=-1)
    return jnp.concatenate([top, jnp.zeros_like(top[..., :1, :])], axis=-2)


def vee(matrix):
    return jnp.concatenate([matrix[..., :3, 3], unskew(matrix[..., :3, :3])], axis=-1)


def _as_matrix(params):
    """$T = [R(q), t; 0, 1]$."""
    q, t = _split(params)
    top = jnp.concatenate([quat_to_matrix(q), t[..., None]], axis=-1)
    bottom = jnp.broadcast_to(
        jnp.array([0.0, 0.0, 0.0, 1.0], dtype=params.dtype), top[..., :1, :].shape
    )
    return jnp.concatenate([top, bottom], axis=-2)


def _from_matrix(matrix):
    """Rotation by `SO3.from_matrix` (re-orthogonalized), translation the last column."""
    return _join(so3.from_matrix(matrix[..., :3, :3]), matrix[..., :3, 3])


def _normalize(params):
    """Unit quaternion, translation unchanged."""
    q, t = _split(params)
    return jnp.concatenate([so3.normalize(q), t], axis=-1)


# The generic rules (lieax.groups._generic) for all but compose, inverse and act, whose closed
# forms above avoid the 6×6 adjoint (they are what benchmarks/chain.py times).
_ops = _generic.local_rules(
    sys.modules[__name__], exp=_exp, log=_log, compose=compose, inverse=inverse,
    adjoint=_adjoint, as_matrix=_as_matrix, from_matrix=_from_matrix, normalize=_normalize,
)  # fmt: skip
exp, log, adjoint, as_matrix = _ops.exp, _ops.log, _ops.adjoint, _ops.as_matrix
from_matrix, normalize = _ops.from_matrix, _ops.normalize
to_parameters, from_parameters = _ops.to_parameters, _ops.from_parameters


def sample_uniform(key, batch_shape, dtype):
    """Uniform rotation (Haar) and translation uniform in $[-1, 1]^3$."""
    key_rotation, key_translation = jax.random.split(key)
    q = so3.sample_uniform(key_rotation, batch_shape, dtype)
    t = jax.random.uniform(
        key_translation, (*batch_shape, 3), dtype=q.dtype, minval=-1.0, maxval=1.0
    )
    return jnp.concatenate([q, t], axis=-1)


class SE3(AbstractGroup):
    """Rigid motions in 3D: parameters `(w, x, y, z, tx, ty, tz)`, shape `(*batch, 7)`; tangent
    `(vx, vy, vz, ωx, ωy, ωz)`, shape `(*batch, 6)`."""

    tangent_dim = 6
    parameters_dim = 7
    space_dim = 3
    matrix_dim = 4
    parameters_layout = "quaternion wxyz, then translation xyz"
    _host_exp = staticmethod(_host.se3_exp)
    _host_from_matrix = staticmethod(
        lambda m: np.concatenate([_host.so3_from_matrix(m[..., :3, :3]), m[..., :3, 3]], -1)
    )

    @property
    def wxyz_xyz(self) -> jax.Array:
        return self.parameters()

    @classmethod
    def from_rotation_and_translation(cls, rotation: SO3, translation: ArrayLike) -> Self:
        """$T = [R, t; 0, 1]$, broadcasting batch shapes (a translation that states no dtype takes
        the rotation's)."""
        name = "SE3.from_rotation_and_translation"
        if not isinstance(rotation, SO3):
            raise TypeError(f"rotation must be an SO3, got {type(rotation).__name__}.")
        translation = match_dtype(
            translation, rotation.dtype, f"{name} translation", "the rotation"
        )
        translation = check_last_axis(translation, 3, f"{name} translation")
        batch = broadcast_batch(name, rotation.batch_shape, translation.shape[:-1])
        if is_concrete(rotation, translation):  # no compilation (`lieax.groups._host`)
            parts = (np.asarray(rotation._params), np.asarray(translation))
            return cls._wrap(to_device(_host.join(batch, *parts)))
        return cls._wrap(join(rotation._params, translation))

    @classmethod
    def from_rotation(cls, rotation: SO3) -> Self:
        return cls.from_rotation_and_translation(rotation, np.zeros(3, dtype=rotation.dtype))

    @classmethod
    def from_translation(cls, translation: ArrayLike) -> Self:
        translation = check_last_axis(translation, 3, "SE3 translation")
        return cls.from_rotation_and_translation(
            SO3.identity(translation.shape[:-1], dtype=translation.dtype), translation
        )

    @overload
    @classmethod
    def align(
        cls,
        points_a: ArrayLike,
        points_b: ArrayLike,
        weights: ArrayLike | None = None,
        *,
        with_scale: Literal[False] = False,
    ) -> Self: ...
    @overload
    @classmethod
    def align(
        cls,
        points_a: ArrayLike,
        points_b: ArrayLike,
        weights: ArrayLike | None = None,
        *,
        with_scale: Literal[True],
    ) -> Sim3: ...
    @overload
    @classmethod
    def align(
        cls,
        points_a: ArrayLike,
        points_b: ArrayLike,
        weights: ArrayLike | None = None,
        *,
        with_scale: bool,
    ) -> Self | Sim3: ...
    @classmethod
    def align(
        cls,
        points_a: ArrayLike,
        points_b: ArrayLike,
        weights: ArrayLike | None = None,
        *,
        with_scale: bool = False,
    ) -> Self | Sim3:
        r"""The least-squares $T_{ab}$ with $a_i \approx T_{ab} b_i$ (SVD of the correlation matrix,
        proper rotation; Umeyama scale and a `Sim3` result with `with_scale`), differentiable with
        respect to the points and weights; see `lieax.align` and `lieax.groups._procrustes`."""
        if with_scale:
            return Sim3.align(points_a, points_b, weights)
        q, t, _ = _procrustes.solve(points_a, points_b, weights, with_scale=False, what="SE3.align")
        return cls._wrap(join(q, t))

    def bearing(self, target: Self | ArrayLike) -> S2:
        r"""The direction of `target` seen from this pose, in the pose's frame, as an `S2`
        (GTSAM's `Pose3::bearing`, which returns a `Unit3`): $d / |d|$ of $d = T^{-1} p$, for
        points $p$ of shape `(*batch, 3)` or the positions $p = t_Y$ of another `SE3` $Y$,
        broadcasting batch shapes.

        Derivatives (rules of `transform_to` and `lieax.groups._bearing_range.direction`; GTSAM's
        Pose3.cpp and Unit3.cpp): with $b = d / |d|$ and $P = (I - b b^\top) / |d|$,
        $\dot b = P\,(-v - \omega \times d + R^\top \dot p)$, so in S2's tangent $B_b$ the blocks are
        $B_b^\top P\,[-I,\ [d]_\times]$ and $B_b^\top P R^\top$ (and $\cdot\,[R_Y, 0]$ for a pose
        target). At $d = 0$: the x axis $(1, 0, 0)$, derivatives 0."""
        points = bearing_range.target_points(self, target, "bearing", 3)
        return S2._wrap(bearing_range.direction(transform_to(self._params, points)))

    def range(self, target: Self | ArrayLike) -> jax.Array:
        r"""The distance $|p - t|$ from this pose to `target`, points of shape `(*batch, 3)` or
        another `SE3`'s position, shape `(*batch,)` (GTSAM's `Pose3::range`). Jacobians
        (right-local): $\partial r / \partial T = (-u^\top R, 0)$, $\partial r / \partial p = u^\top$
        with $u = (p - t) / r$ (and $u^\top R_Y$ on a pose target's translation); at $r = 0$ the
        range is 0 with derivatives 0 (`lieax.groups._bearing_range`)."""
        points = bearing_range.target_points(self, target, "range", 3)
        return bearing_range.norm(points - self.translation())

    def rotation(self) -> SO3:
        return SO3._wrap(self._params[..., :4])

    def translation(self) -> jax.Array:
        return self.parameters()[..., 4:]
