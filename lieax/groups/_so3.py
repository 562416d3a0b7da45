r"""SO(3), rotations in 3D, stored as unit quaternions $q = (w, x, y, z)$ (Hamilton, wxyz).

Tangent $\omega \in \mathbb{R}^3$, right perturbation $q \oplus \omega = q \otimes \mathrm{Exp}(\omega)$.

Tangent carrier. JAX gives the quaternion leaf a 4-vector tangent; lieax fills it with the local
coordinates themselves, $(\rho, \omega)$ with $\dot q = q \otimes (\rho, \omega/2)$ ($\rho$ the radial
part, zero on the manifold). Kernels therefore read and write local tangents directly and no rule
converts anything; the conversion to and from the derivative of the raw quaternion happens only
where raw parameters cross the API: `SO3(wxyz)` (`from_parameters`) and `X.parameters()`
(`to_parameters`), the generic maps of `lieax.groups._generic` from `carrier_from_raw` and
`raw_from_carrier`. Code that differentiates the raw quaternion still gets exact derivatives.
Inside rules, anything that depends on $q$ is computed by kernels (`as_matrix`) or from
`to_parameters(q)`, so second derivatives stay consistent with the carrier.

Formulas: Solà, Deray, Atchuthan, "A micro Lie theory for state estimation in robotics" (2018),
Sec. IV-B and App. B; the coefficients are the $g_n$ of `lieax.groups._series`.
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
    to_device,
)
from .._linalg import (
    cross,
    dot,
    matvec,
    quat_conjugate,
    quat_multiply,
    quat_to_matrix,
    rotate_back,
    skew,
    unskew,
)
from . import _generic, _host, _rules
from ._base import AbstractGroup
from ._series import (
    HALF_ANGLE_SERIES_LIMIT,
    exp_coefficients,
    g,
    jr_inverse_d_series,
)


def carrier_from_raw(q, q_dot):
    r"""The carrier of a raw quaternion derivative: $(\rho, \omega) = (\mathrm{Re}, 2\,\mathrm{Im})(q^{-1} \otimes \dot q)$."""
    product = quat_multiply(quat_conjugate(q), q_dot) / dot(q, q)[..., None]
    return product * jnp.array([1.0, 2.0, 2.0, 2.0], dtype=product.dtype)


def raw_from_carrier(q, carrier):
    r"""The raw quaternion derivative of a carrier: $\dot q = q \otimes (\rho, \omega / 2)$, inverse of
    `carrier_from_raw`."""
    return quat_multiply(q, carrier * jnp.array([1.0, 0.5, 0.5, 0.5], dtype=carrier.dtype))


def unit_rotation(q):
    """$R(q / |q|)$ of a raw quaternion, by plain array operations: the carrier maps read raw
    parameters, whose derivatives are raw (the `normalize` and `as_matrix` kernels would read them
    as carriers, and second derivatives through `parameters()` would be wrong)."""
    return quat_to_matrix(q / jnp.sqrt(dot(q, q))[..., None])


def to_local(q, carrier):
    r"""The right-local tangent $\omega$ held by a carrier."""
    return carrier[..., 1:]


def from_local(q, omega):
    r"""The carrier of a right-local tangent: $(0, \omega)$."""
    return jnp.concatenate([jnp.zeros_like(omega[..., :1]), omega], axis=-1)


# ---- coefficient matrices -----------------------------------------------------------------------


def jr_inverse_coefficient(s):
    r"""$D(\theta) = 1/\theta^2 - (1 + \cos\theta) / (2\theta\sin\theta) = (g_3 - 2g_4) / (2g_2)$
    (finite up to $\theta < 2\pi$; $1/12$ at zero)."""
    return (g(3, s) - 2.0 * g(4, s)) / (2.0 * g(2, s))


def right_jacobian(omega):
    r"""$J_r(\omega) = I - g_2 [\omega]_\times + g_3 [\omega]_\times^2$ (Solà eq. 143)."""
    s = dot(omega, omega)[..., None, None]
    w = skew(omega)
    return jnp.eye(3, dtype=omega.dtype) - g(2, s) * w + g(3, s) * (w @ w)


def right_jacobian_inverse(omega):
    r"""$J_r^{-1}(\omega) = I + \tfrac12 [\omega]_\times + D(\theta) [\omega]_\times^2$ (Solà eq. 144)."""
    s = dot(omega, omega)[..., None, None]
    w = skew(omega)
    return jnp.eye(3, dtype=omega.dtype) + 0.5 * w + jr_inverse_coefficient(s) * (w @ w)


def apply_right_jacobian(omega, x):
    r"""$J_r(\omega)\,x$ without forming the matrix."""
    s = dot(omega, omega)[..., None]
    wx = cross(omega, x)
    return x - g(2, s) * wx + g(3, s) * cross(omega, wx)


def apply_right_jacobian_inverse(omega, x):
    r"""$J_r^{-1}(\omega)\,x$ without forming the matrix."""
    s = dot(omega, omega)[..., None]
    wx = cross(omega, x)
    return x + 0.5 * wx + jr_inverse_coefficient(s) * cross(omega, wx)


# ---- fused closed forms: Exp with J_r, Log with J_r^{-1}, one set of coefficients ---------------


def _square_skew(omega, s):
    r"""$[\omega]_\times^2 = \omega\omega^\top - \theta^2 I$ written out (no 3×3 product)."""
    return omega[..., :, None] * omega[..., None, :] - s[..., None, None] * jnp.eye(
        3, dtype=omega.dtype
    )


@jax.custom_jvp
def exp_and_right_jacobian(omega):
    r"""$(\mathrm{Exp}(\omega), J_r(\omega))$, the quaternion `(*batch, 4)` and `(*batch, 3, 3)`,
    from one cosine and one sine of $\theta/2$:
    $q = (\cos\tfrac\theta2, h\,\omega)$ with $h = \sin(\theta/2)/\theta$ (as `exp`), and
    $J_r = I - g_2[\omega]_\times + g_3[\omega]_\times^2$ (Solà eq. 143) with
    $g_1 = \sin\theta/\theta = 2h\cos\tfrac\theta2$, $g_2 = (1 - \cos\theta)/\theta^2 = 2h^2$
    (the half-angle identities $\sin\theta = 2\sin\tfrac\theta2\cos\tfrac\theta2$,
    $1 - \cos\theta = 2\sin^2\tfrac\theta2$) and $g_3 = (\theta - \sin\theta)/\theta^3 =
    (1 - g_1)/\theta^2$; below $\theta^2 = 0.25$ their Taylor series in $\theta^2$ (`lieax.groups._series`'s
    $g_n$). Exact at $\pi$ and beyond (no division by $\sin$). Derivatives: the carrier of
    $\dot q$ is $J_r\dot\omega$ (`exp`'s rule), that of $J_r$ is `right_jacobian`'s."""
    s = dot(omega, omega)
    half_cos, half_sinc, _, g2, g3 = exp_coefficients(s)
    q = jnp.concatenate([half_cos[..., None], half_sinc[..., None] * omega], axis=-1)
    jr = (
        jnp.eye(3, dtype=omega.dtype)
        - g2[..., None, None] * skew(omega)
        + g3[..., None, None] * _square_skew(omega, s)
    )
    return q, jr


@exp_and_right_jacobian.defjvp
def _exp_and_right_jacobian_jvp(primals, tangents):
    (omega,), (omega_dot,) = primals, tangents
    q, jr = exp_and_right_jacobian(omega)
    _, jr_dot = jax.jvp(right_jacobian, (omega,), (omega_dot,))
    return (q, jr), (from_local(q, matvec(jr, omega_dot)), jr_dot)


@jax.custom_jvp
def log_and_right_jacobian_inverse(q):
    r"""$(\mathrm{Log}(q), J_r^{-1}(\mathrm{Log}(q)))$, `(*batch, 3)` and `(*batch, 3, 3)`, from
    one `atan2`: $\omega$ as `log` ($\theta = 2\,\mathrm{atan2}(|u|, |w|) \le \pi$), and
    $J_r^{-1} = I + \tfrac12[\omega]_\times + D[\omega]_\times^2$ (Solà eq. 144) with
    $D = 1/\theta^2 - (1 + \cos\theta)/(2\theta\sin\theta) = 1/\theta^2 - \cot(\theta/2)/(2\theta)
    = (1 - \theta|w| / (2|u|))/\theta^2$ ($\cot\tfrac\theta2 = |w|/|u|$ for any scale of $q$);
    below $\theta^2 = 0.25$ its Taylor series $\sum_{k \ge 1} |B_{2k}|\theta^{2k-2}/(2k)!$ (the
    Laurent series of $\cot$; Abramowitz and Stegun 4.3.70), $1/12$ at zero. Stable near $\pi$
    ($D \to 1/\pi^2$, $|w| \to 0$). Derivatives: $\dot\omega = J_r^{-1}$ times the carrier of
    $\dot q$ (`log`'s rule), that of $J_r^{-1}$ is `right_jacobian_inverse`'s."""
    w, u = q[..., 0], q[..., 1:]
    norm_u = jnp.sqrt(dot(u, u))
    nonzero = norm_u > 0
    safe_norm = jnp.where(nonzero, norm_u, 1.0)
    abs_w = jnp.abs(w)
    half = jnp.arctan2(norm_u, abs_w)
    scale = jnp.where(nonzero, 2.0 * half / safe_norm, 2.0 / abs_w)
    omega = jnp.where(w < 0, -scale, scale)[..., None] * u
    theta = 2.0 * half
    s = theta * theta
    small = s < HALF_ANGLE_SERIES_LIMIT
    theta_safe = jnp.where(small, 1.0, theta)
    d = jnp.where(
        small,
        jr_inverse_d_series(s),
        (1.0 - 0.5 * theta_safe * abs_w / jnp.where(small, 1.0, norm_u))
        / (theta_safe * theta_safe),
    )
    jr_inv = (
        jnp.eye(3, dtype=q.dtype)
        + 0.5 * skew(omega)
        + d[..., None, None] * _square_skew(omega, dot(omega, omega))
    )
    return omega, jr_inv


@log_and_right_jacobian_inverse.defjvp
def _log_and_right_jacobian_inverse_jvp(primals, tangents):
    (q,), (q_dot,) = primals, tangents
    omega, jr_inv = log_and_right_jacobian_inverse(q)
    omega_dot = matvec(jr_inv, to_local(q, q_dot))
    _, jr_inv_dot = jax.jvp(right_jacobian_inverse, (omega,), (omega_dot,))
    return (omega, jr_inv), (omega_dot, jr_inv_dot)


# ---- kernels with closed-form rules -------------------------------------------------------------


@jax.custom_jvp
def exp(omega):
    r"""$\mathrm{Exp}(\omega) = (\cos\tfrac\theta2,\ \tfrac{\sin(\theta/2)}{\theta}\,\omega)
    = (g_0(s/4),\ \tfrac12 g_1(s/4)\,\omega)$, $s = \theta^2$."""
    quarter = 0.25 * dot(omega, omega)[..., None]
    return jnp.concatenate([g(0, quarter), 0.5 * g(1, quarter) * omega], axis=-1)


@exp.defjvp
def _exp_jvp(primals, tangents):
    (omega,), (omega_dot,) = primals, tangents
    q = exp(omega)
    return q, from_local(q, apply_right_jacobian(omega, omega_dot))


@jax.custom_jvp
def log(q):
    r"""$\mathrm{Log}(q) = 2\,\mathrm{sign}(w)\,\mathrm{atan2}(|u|, |w|)\,u / |u|$, $\theta \le \pi$;
    $2u/|w|$ where $u = 0$."""
    w, u = q[..., :1], q[..., 1:]
    norm_u = jnp.sqrt(dot(u, u))[..., None]
    nonzero = norm_u > 0
    safe_norm = jnp.where(nonzero, norm_u, 1.0)
    abs_w = jnp.abs(w)
    scale = jnp.where(nonzero, 2.0 * jnp.arctan2(norm_u, abs_w) / safe_norm, 2.0 / abs_w)
    return jnp.where(w < 0, -scale, scale) * u


@log.defjvp
def _log_jvp(primals, tangents):
    (q,), (q_dot,) = primals, tangents
    omega = log(q)
    return omega, apply_right_jacobian_inverse(omega, to_local(q, q_dot))


@jax.custom_jvp
def compose(q1, q2):
    r"""$q_1 \otimes q_2$."""
    return quat_multiply(q1, q2)


@_rules.defjvp(compose)
def _compose_jvp(primals, tangents):
    r"""Local block: $\omega = R_2^\top \omega_1 + \omega_2$ (Solà eq. 171-172)."""
    (q1, q2), (q1_dot, q2_dot) = primals, tangents
    q = compose(q1, q2)
    omega1 = _rules.local_tangent(to_local, q1, q1_dot)
    omega2 = _rules.local_tangent(to_local, q2, q2_dot)
    rotated = None if omega1 is None else rotate_back(as_matrix(q2), omega1)
    omega = _rules.add(rotated, omega2)
    return _rules.finish(q, None if omega is None else from_local(q, omega))


@jax.custom_jvp
def inverse(q):
    r"""$\bar q$."""
    return quat_conjugate(q)


@inverse.defjvp
def _inverse_jvp(primals, tangents):
    r"""Local block: $\omega_{out} = -R\,\omega$ (Solà eq. 140)."""
    (q,), (q_dot,) = primals, tangents
    q_inv = inverse(q)
    return q_inv, from_local(q_inv, -matvec(as_matrix(q), to_local(q, q_dot)))


@jax.custom_jvp
def act(q, points):
    r"""$R(q)\,p$."""
    return matvec(quat_to_matrix(q), points)


@_rules.defjvp(act)
def _act_jvp(primals, tangents):
    r"""$\dot y = R(\omega \times p + \dot p)$: blocks $-R[p]_\times$ and $R$ (Solà eq. 146-147)."""
    (q, points), (q_dot, points_dot) = primals, tangents
    moved = act(q, points)
    omega = _rules.local_tangent(to_local, q, q_dot)
    direction = _rules.add(
        None if omega is None else cross(omega, points),
        None if _rules.is_zero(points_dot) else points_dot,
    )
    if direction is None:
        return _rules.finish(moved, None)
    return _rules.finish(moved, matvec(as_matrix(q), direction))


def _from_matrix(rotation):
    r"""Shepperd's method: build $q$ from the largest of $1 + \mathrm{tr} R$ and $1 + 2R_{ii} - \mathrm{tr} R$,
    then normalize (a valid rotation for any input; exact for a rotation matrix)."""
    m = rotation
    m00, m11, m22 = m[..., 0, 0], m[..., 1, 1], m[..., 2, 2]
    candidates = jnp.stack(
        [
            jnp.stack(
                [
                    1 + m00 + m11 + m22,
                    m[..., 2, 1] - m[..., 1, 2],
                    m[..., 0, 2] - m[..., 2, 0],
                    m[..., 1, 0] - m[..., 0, 1],
                ],
                axis=-1,
            ),
            jnp.stack(
                [
                    m[..., 2, 1] - m[..., 1, 2],
                    1 + m00 - m11 - m22,
                    m[..., 1, 0] + m[..., 0, 1],
                    m[..., 0, 2] + m[..., 2, 0],
                ],
                axis=-1,
            ),
            jnp.stack(
                [
                    m[..., 0, 2] - m[..., 2, 0],
                    m[..., 1, 0] + m[..., 0, 1],
                    1 - m00 + m11 - m22,
                    m[..., 2, 1] + m[..., 1, 2],
                ],
                axis=-1,
            ),
            jnp.stack(
                [
                    m[..., 1, 0] - m[..., 0, 1],
                    m[..., 0, 2] + m[..., 2, 0],
                    m[..., 2, 1] + m[..., 1, 2],
                    1 - m00 - m11 + m22,
                ],
                axis=-1,
            ),
        ],
        axis=-2,
    )
    pivots = jnp.stack(
        [1 + m00 + m11 + m22, 1 + m00 - m11 - m22, 1 - m00 + m11 - m22, 1 - m00 - m11 + m22],
        axis=-1,
    )
    best = jnp.argmax(pivots, axis=-1)
    q = jnp.take_along_axis(candidates, best[..., None, None], axis=-2)[..., 0, :]
    return normalize(q)


def _normalize(q):
    """$q / |q|$."""
    return q / jnp.linalg.norm(q, axis=-1, keepdims=True)


def hat(omega):
    return skew(omega)


def vee(matrix):
    return unskew(matrix)


ad = hat  # ad_ω = [ω]×


# The generic rules (lieax.groups._generic) for the matrix ($R(q)$, also $\\mathrm{Ad}_R$),
# `from_matrix` and `normalize`; exp, log, compose, inverse and act keep the vector closed forms
# above (no 3×3 Jacobian formed; what benchmarks/chain.py times).
_ops = _generic.local_rules(
    sys.modules[__name__], exp=exp, log=log, compose=compose, inverse=inverse,
    adjoint=quat_to_matrix, as_matrix=quat_to_matrix, from_matrix=_from_matrix,
    normalize=_normalize,
)  # fmt: skip
as_matrix, from_matrix, normalize = _ops.as_matrix, _ops.from_matrix, _ops.normalize
to_parameters, from_parameters = _ops.to_parameters, _ops.from_parameters
adjoint = as_matrix  # Ad_R = R


def sample_uniform(key, batch_shape, dtype):
    """Uniform rotations: a normalized standard normal 4-vector (Shoemake)."""
    return normalize(jax.random.normal(key, (*batch_shape, 4), dtype=dtype))


# ---- the Cayley transform on unit quaternions (the kernels of `lieax.retractions.cayley`) ---------------------------------------------------


@jax.custom_jvp
def cayley_quaternion(omega):
    r"""$\mathrm{cay}(\omega)$ as a unit quaternion: $q = (2, \omega) / \sqrt{4 + |\omega|^2}$,
    i.e. $(1, \omega/2)$ normalized, $\tan(\alpha/2) = |\omega|/2$ for the rotation angle
    $\alpha$. Its matrix is GTSAM's `Rot3::CayleyChart::Retract`,
    $[(4 - |\omega|^2) I + 2\omega\omega^\top + 4[\omega]_\times] / (4 + |\omega|^2)$."""
    n = jnp.sqrt(4.0 + dot(omega, omega))[..., None]
    return jnp.concatenate([2.0 / n, omega / n], axis=-1)


@cayley_quaternion.defjvp
def _cayley_quaternion_jvp(primals, tangents):
    r"""Local block (the Cayley map's right Jacobian, $\mathrm{cay}(\omega + \dot\omega) \approx
    \mathrm{cay}(\omega)\,\mathrm{Exp}(J\dot\omega)$): with $q = (a, u)$,
    $2\,\mathrm{Im}(\bar q \otimes \dot q) = 2(a\dot u - \dot a u - u \times \dot u)$ gives
    $J = \frac{4}{4 + |\omega|^2}\,(I - \tfrac12[\omega]_\times)$ (the identity at zero)."""
    (omega,), (omega_dot,) = primals, tangents
    q = cayley_quaternion(omega)
    factor = (4.0 / (4.0 + dot(omega, omega)))[..., None]
    local = factor * (omega_dot - 0.5 * cross(omega, omega_dot))
    return q, from_local(q, local)


@jax.custom_jvp
def cayley_quaternion_inverse(q):
    r"""$\mathrm{cay}^{-1}(q) = 2\,u / w$ for $q = (w, u)$: the Gibbs vector of the rotation,
    $2\tan(\alpha/2)$ along the axis; the same for $q$ and $-q$ (no sign to fix), and scale-free
    (any nonzero multiple of a unit quaternion). Defined for rotation angles below $\pi$ ($w \ne 0$);
    it grows without bound as the angle nears $\pi$ (GTSAM's `Rot3::CayleyChart::Local`)."""
    return 2.0 * q[..., 1:] / q[..., :1]


@cayley_quaternion_inverse.defjvp
def _cayley_quaternion_inverse_jvp(primals, tangents):
    r"""$\dot\omega = J^{-1}\omega_{local} = \omega_{local} + \tfrac12 \omega \times \omega_{local}
    + \tfrac14 \omega\,(\omega^\top \omega_{local})$, the inverse of `cayley_quaternion`'s block
    ($(I - \tfrac12[\omega]_\times)^{-1} = I + (2[\omega]_\times + [\omega]_\times^2)/(4 + |\omega|^2)$);
    the radial part of the carrier does not move $u / w$."""
    (q,), (carrier,) = primals, tangents
    omega = cayley_quaternion_inverse(q)
    local = to_local(q, carrier)
    omega_dot = local + 0.5 * cross(omega, local) + 0.25 * omega * dot(omega, local)[..., None]
    return omega, omega_dot


class SO3(AbstractGroup):
    r"""Rotations in 3D: parameters `wxyz`, shape `(*batch, 4)`; tangent $\omega$, shape `(*batch, 3)`."""

    tangent_dim = 3
    parameters_dim = 4
    space_dim = 3
    matrix_dim = 3
    parameters_layout = "unit quaternion wxyz"
    _host_exp = staticmethod(_host.so3_exp)
    _host_from_matrix = staticmethod(_host.so3_from_matrix)

    @property
    def wxyz(self) -> jax.Array:
        return self.parameters()

    @classmethod
    def from_xyzw(cls, xyzw: ArrayLike) -> Self:
        """From scalar-last quaternions (SciPy, ROS, Eigen's `coeffs()`)."""
        xyzw = check_last_axis(xyzw, 4, "SO3.from_xyzw quaternion", "xyzw")
        if is_concrete(xyzw):  # no compilation (`lieax.groups._host`)
            return cls(np.roll(np.asarray(xyzw), 1, axis=-1))
        return cls(jnp.roll(xyzw, 1, axis=-1))

    def as_xyzw(self) -> jax.Array:
        """Scalar-last quaternions (SciPy, ROS, Eigen's `coeffs()`)."""
        return jnp.roll(self.parameters(), -1, axis=-1)

    @classmethod
    def from_rotvec(cls, rotvec: ArrayLike) -> Self:
        """From axis times angle (the same as `exp`)."""
        return cls.exp(rotvec)

    def as_rotvec(self) -> jax.Array:
        r"""Axis times angle, angle in $[0, \pi]$ (the same as `log`)."""
        return self.log()

    @classmethod
    def from_rpy(cls, roll: ArrayLike, pitch: ArrayLike, yaw: ArrayLike) -> Self:
        r"""$R = R_z(\text{yaw})\,R_y(\text{pitch})\,R_x(\text{roll})$ (extrinsic x-y-z, as ROS), angles
        of shapes that broadcast; the dtype is that of the arrays among them (Python and NumPy
        numbers take it)."""
        if is_concrete(roll, pitch, yaw):  # no compilation (`lieax.groups._host`)
            roll, pitch, yaw = common_host_arrays("SO3.from_rpy", roll, pitch, yaw)
            batch = broadcast_batch("SO3.from_rpy", roll.shape, pitch.shape, yaw.shape)
            zero = np.zeros(batch, roll.dtype)
            about = lambda a, b, c: _host.so3_exp(np.stack(np.broadcast_arrays(a, b, c), -1))  # noqa: E731
            q = _host.quaternion_product(about(zero, zero, yaw), about(zero, pitch, zero))
            return cls._wrap(to_device(_host.quaternion_product(q, about(roll, zero, zero))))
        roll, pitch, yaw = common_float_arrays("SO3.from_rpy", roll, pitch, yaw)
        batch = broadcast_batch("SO3.from_rpy", roll.shape, pitch.shape, yaw.shape)
        roll, pitch, yaw = (jnp.broadcast_to(a, batch) for a in (roll, pitch, yaw))
        zero = jnp.zeros_like(roll)
        about = lambda a, b, c: cls.exp(jnp.stack([a, b, c], axis=-1))  # noqa: E731
        return about(zero, zero, yaw) @ about(zero, pitch, zero) @ about(roll, zero, zero)

    @classmethod
    def exp_and_right_jacobian(cls, tangent: ArrayLike) -> tuple[Self, jax.Array]:
        r"""`(SO3.exp(tangent), SO3.right_jacobian(tangent))` from one set of coefficients
        (`exp_and_right_jacobian`)."""
        tangent = check_last_axis(tangent, 3, "SO3.exp_and_right_jacobian tangent")
        q, jr = exp_and_right_jacobian(tangent)
        return cls._wrap(q), jr

    def log_and_right_jacobian_inverse(self) -> tuple[jax.Array, jax.Array]:
        r"""`(X.log(), SO3.right_jacobian_inverse(X.log()))` from one `atan2`
        (`log_and_right_jacobian_inverse`)."""
        return log_and_right_jacobian_inverse(self._params)

    def as_rpy(self) -> jax.Array:
        r"""`(roll, pitch, yaw)` on the last axis, inverse of `from_rpy` (pitch in $[-\pi/2, \pi/2]$)."""
        r = self.as_matrix()
        roll = jnp.arctan2(r[..., 2, 1], r[..., 2, 2])
        pitch = jnp.arcsin(jnp.clip(-r[..., 2, 0], -1.0, 1.0))
        yaw = jnp.arctan2(r[..., 1, 0], r[..., 0, 0])
        return jnp.stack([roll, pitch, yaw], axis=-1)
