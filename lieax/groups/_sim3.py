r"""Sim(3), similarity transforms in 3D, stored as `(w, x, y, z, tx, ty, tz, σ)`: a unit quaternion
(wxyz), a translation and the log-scale $\sigma$, $T = [e^\sigma R(q), t; 0, 1]$, so that
$T p = s R p + t$ with $s = e^\sigma$.

Tangent $\xi = (v, \omega, \sigma)$ (translation, rotation, log-scale), with
$\xi^\wedge = [[\omega]_\times + \sigma I, v; 0, 0]$; right perturbation
$T \oplus \xi = T\,\mathrm{Exp}(\xi)$, so $\dot t = s R v$, $\dot q = q \otimes (0, \omega/2)$ and
$\dot\sigma = \sigma_\xi$.

Tangent carrier (see `lieax.groups._so3` and `lieax.groups._se3`): the 8-vector tangent of the parameter leaf holds
$(\rho, \omega, v, \sigma)$, aligned with the parameter slots: SO3's carrier in the quaternion slot,
the local translation $v$ in the translation slot and $\dot\sigma$ in the scale slot. Kernels use
local tangents without conversion; `Sim3(params)`, `parameters()`, `translation()`, `log_scale()`
and `from_rotation_translation_scale` convert where raw arrays cross the API.

Formulas.
- $\mathrm{Exp}(v, \omega, \sigma) = (\mathrm{Exp}(\omega), W v, \sigma)$ with
  $W = \int_0^1 e^{\sigma\tau} R(\tau\omega)\,d\tau = A I + B [\omega]_\times + C [\omega]_\times^2$
  (Eade, "Lie groups for 2D and 3D transformations", Sim(3) section), where, with $s = \theta^2$,
  $A = (e^\sigma - 1)/\sigma$,
  $B = \int_0^1 e^{\sigma\tau} \sin(\tau\theta)/\theta\,d\tau = (e^\sigma(\sigma g_1 - g_0) + 1)/(\sigma^2 + s)$,
  $C = \int_0^1 e^{\sigma\tau} (1 - \cos\tau\theta)/\theta^2\,d\tau$
  $= (A - (e^\sigma(\sigma g_0 + s g_1) - \sigma)/(\sigma^2 + s))/s$
  $= (e^\sigma(\sigma^2 g_2 + 1 - \sigma g_1) - 1)/(\sigma(\sigma^2 + s))$
  ($g_n$ the coefficients of `lieax.groups._series`). Each closed form is used only where its divisor
  is at least 1 and dominant (for $C$: the division by $\sigma$ where $\sigma^2 \ge \max(1, s)$,
  by $s$ where $s \ge \max(1, \sigma^2)$); near $\sigma = \theta = 0$ the double series
  $\sum_{k,m} (-s)^k \sigma^m / (m!\,n_k!\,(m + n_k + 1))$ of the integrals is summed (both branches
  evaluated on safe inputs and masked, so no NaN in values or derivatives).
- $\mathrm{Ad}_T = [[sR, [t]_\times R, -t], [0, R, 0], [0, 0, 1]]$,
  $\mathrm{ad}_\xi = [[[\omega]_\times + \sigma I, [v]_\times, -v], [0, [\omega]_\times, 0], [0, 0, 0]]$.
- $J_r(\xi) = \varphi_1(-\mathrm{ad}_\xi) = \sum_k (-\mathrm{ad}_\xi)^k / (k + 1)!$. Its
  translation/rotation coupling block has no short closed form in $(\sigma, \theta)$ (it is a
  double integral of $e^{\sigma u} R(u\omega)[v]_\times R(w\omega)$, whose $\sigma = 0$ case is
  Barfoot's $Q$; written out it needs about ten two-variable coefficients, each with its own
  cancellations), so $\varphi_1$ of the 7×7 matrix is evaluated numerically by scaling and
  doubling (`phi1_matrix`): accurate to rounding for any tangent of practical size, NaN-free at 0,
  and differentiable in every mode (so second derivatives of the rules work). It gives the same
  values (to 3e-14) as the top-right block of the 14×14 `expm([[-ad, I], [0, 0]])`, which was
  measured 3.5× slower on a batch of 2000 tangents (CPU, float64) and slower to compile. $J_r^{-1}$ is its inverse
  (`jnp.linalg.inv`). Only `exp` and `log` (and the Jacobian functions) use them; compose,
  inverse, act, adjoint and the matrices have closed-form blocks.
"""

import math
import sys
from typing import Protocol, Self

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax
from jax.typing import ArrayLike

from .._checks import as_float_array, broadcast_batch, check_last_axis, check_positive, match_dtype
from .._linalg import (
    blocks,
    cross,
    dot,
    horner,
    matvec,
    quat_conjugate,
    quat_multiply,
    quat_rotate,
    quat_to_matrix,
    rotate_back,
    skew,
    unskew,
)
from . import _generic, _procrustes, _rules
from . import _so3 as so3
from ._base import AbstractGroup
from ._series import g
from ._so3 import SO3

# ---- the coefficients of W = A I + B [ω]x + C [ω]x² ---------------------------------------------

_CLOSED_LIMIT = 1.0  # a closed form is used where its divisor (σ², θ², σ² + θ²) is at least this
_SIGMA_TERMS = 20  # 1/20! < 1e-18: the σ series for |σ| < 1
_ANGLE_TERMS = 11  # 1/(2·10 + 1)! < 1e-19: the θ² series for θ² < 1


def _double_series_table(offset: int) -> np.ndarray:
    r"""Coefficients $T_{km} = (-1)^k / (m!\,n!\,(m + n + 1))$ with $n = 2k + \text{offset}$ of
    $\sum_{k,m} T_{km} s^k \sigma^m = \sum_k (-s)^k \int_0^1 e^{\sigma\tau} \tau^n / n!\,d\tau$."""
    table = np.zeros((_ANGLE_TERMS, _SIGMA_TERMS))
    for k in range(_ANGLE_TERMS):
        n = 2 * k + offset
        for m in range(_SIGMA_TERMS):
            table[k, m] = (-1) ** k / (math.factorial(m) * math.factorial(n) * (m + n + 1))
    return table


_B_TABLE = _double_series_table(1)
_C_TABLE = _double_series_table(2)


def _powers(x, count):
    r"""$(1, x, \dots, x^{count-1})$ on a new last axis (products only: derivatives NaN-free at 0;
    `jax.lax` products, as `lieax._linalg.horner`)."""
    powers = [jnp.ones_like(x)]
    for _ in range(count - 1):
        powers.append(lax.mul(powers[-1], x))
    return jnp.stack(powers, axis=-1)


def _double_series(table, s_powers, sigma_powers):
    r"""$\sum_{k,m} T_{km} s^k \sigma^m$ from the `_powers` of $s$ and $\sigma$."""
    table = jnp.asarray(table, dtype=sigma_powers.dtype)
    return jnp.einsum("...k,km,...m->...", s_powers, table, sigma_powers)


def phi1(sigma):
    r"""$A(\sigma) = (e^\sigma - 1)/\sigma = \sum_m \sigma^m / (m + 1)!$ (1 at zero)."""
    small = jnp.abs(sigma) < 1.0
    sigma_series = jnp.where(small, sigma, 0.0)
    sigma_closed = jnp.where(small, 1.0, sigma)
    series = horner([1.0 / math.factorial(m + 1) for m in range(_SIGMA_TERMS)], sigma_series)
    return jnp.where(small, series, jnp.expm1(sigma_closed) / sigma_closed)


def w_coefficients(sigma, s):
    r"""$(A, B, C)$ of $W(\sigma, \omega) = A I + B [\omega]_\times + C [\omega]_\times^2$, with
    $s = \theta^2$ (module docstring); finite with finite derivatives of any order everywhere."""
    sigma2 = sigma * sigma
    a = phi1(sigma)
    in_series = (sigma2 < _CLOSED_LIMIT) & (s < _CLOSED_LIMIT)
    # g_n is finite with finite derivatives at every s >= 0, so each g_n is evaluated once, at s
    # itself: only the divisors need the masked ("safe") inputs of the double where
    g0, g1, g2 = g(0, s), g(1, s), g(2, s)
    sigma_series = jnp.where(in_series, sigma, 0.0)
    s_series = jnp.where(in_series, s, 0.0)
    s_powers = _powers(s_series, _ANGLE_TERMS)
    sigma_powers = _powers(sigma_series, _SIGMA_TERMS)

    # B: closed form wherever σ² + s >= 1 (outside the series square, σ² + s >= 1 holds).
    safe_sigma_b = jnp.where(in_series, 1.0, sigma)
    safe_s_b = jnp.where(in_series, 0.0, s)
    e = jnp.exp(safe_sigma_b)
    b_closed = (e * (safe_sigma_b * g1 - g0) + 1.0) / (safe_sigma_b * safe_sigma_b + safe_s_b)
    b = jnp.where(in_series, _double_series(_B_TABLE, s_powers, sigma_powers), b_closed)

    # C: dividing by σ where σ² >= max(1, s), by s where s >= max(1, σ²) (each without
    # cancellation there), else the series.
    by_sigma = (sigma2 >= _CLOSED_LIMIT) & (sigma2 >= s)
    by_s = ~by_sigma & (s >= _CLOSED_LIMIT)
    sigma_s = jnp.where(by_s, sigma, 0.0)
    s_s = jnp.where(by_s, s, _CLOSED_LIMIT)
    e_s = jnp.exp(sigma_s)
    cos_part = (e_s * (sigma_s * g0 + s_s * g1) - sigma_s) / (sigma_s * sigma_s + s_s)
    c_by_s = (a - cos_part) / s_s  # (A = phi1(σ) is finite with finite derivatives at every σ)
    sigma_a = jnp.where(by_sigma, sigma, 1.0)
    s_a = jnp.where(by_sigma, s, 0.0)
    e_a = jnp.exp(sigma_a)
    c_by_sigma = (e_a * (sigma_a * sigma_a * g2 + 1.0 - sigma_a * g1) - 1.0) / (
        sigma_a * (sigma_a * sigma_a + s_a)
    )
    c_series = _double_series(_C_TABLE, s_powers, sigma_powers)
    c = jnp.where(by_s, c_by_s, jnp.where(by_sigma, c_by_sigma, c_series))
    return a, b, c


def apply_w(sigma, omega, x):
    r"""$W(\sigma, \omega)\,x = A x + B\,\omega \times x + C\,\omega \times (\omega \times x)$."""
    a, b, c = w_coefficients(sigma[..., None], dot(omega, omega)[..., None])
    wx = cross(omega, x)
    return a * x + b * wx + c * cross(omega, wx)


def w_matrix(sigma, omega):
    r"""$W(\sigma, \omega)$ as a matrix, shape `(*batch, 3, 3)`."""
    a, b, c = w_coefficients(sigma[..., None, None], dot(omega, omega)[..., None, None])
    w = skew(omega)
    return a * jnp.eye(3, dtype=omega.dtype) + b * w + c * (w @ w)


def _solve3(matrix, x):
    r"""$M^{-1} x$ for 3×3 matrices by the adjugate: rows $r_i$, $M^{-1} = [r_1 \times r_2, r_2 \times r_0,
    r_0 \times r_1] / \det M$."""
    r0, r1, r2 = matrix[..., 0, :], matrix[..., 1, :], matrix[..., 2, :]
    c0, c1, c2 = cross(r1, r2), cross(r2, r0), cross(r0, r1)
    det = dot(r0, c0)[..., None]
    return (c0 * x[..., :1] + c1 * x[..., 1:2] + c2 * x[..., 2:]) / det


# ---- parameter and tangent layout ---------------------------------------------------------------


def _split(params):
    return params[..., :4], params[..., 4:7], params[..., 7:]


def _join(q, t, sigma):
    """Parameters from a quaternion, a translation and a log-scale `(*batch, 1)`, broadcasting."""
    batch = jnp.broadcast_shapes(q.shape[:-1], t.shape[:-1], sigma.shape[:-1])
    return jnp.concatenate(
        [
            jnp.broadcast_to(q, (*batch, 4)),
            jnp.broadcast_to(t, (*batch, 3)),
            jnp.broadcast_to(sigma, (*batch, 1)),
        ],
        axis=-1,
    )


def to_local(params, carrier):
    r"""The local tangent $(v, \omega, \sigma)$ held by a carrier $(\rho, \omega, v, \sigma)$."""
    return jnp.concatenate([carrier[..., 4:7], carrier[..., 1:4], carrier[..., 7:]], axis=-1)


def from_local(params, xi):
    r"""The carrier $(0, \omega, v, \sigma)$ of a local tangent $(v, \omega, \sigma)$."""
    return jnp.concatenate(
        [jnp.zeros_like(xi[..., :1]), xi[..., 3:6], xi[..., :3], xi[..., 6:]], axis=-1
    )


def raw_from_carrier(params, carrier):
    r"""The raw derivative of a carrier: $\dot q = q \otimes (\rho, \omega/2)$, $\dot t = s R v$,
    $\dot\sigma = \sigma_\xi$."""
    q, sigma = params[..., :4], params[..., 7:]
    q_dot = so3.raw_from_carrier(q, carrier[..., :4])
    t_dot = jnp.exp(sigma) * matvec(so3.unit_rotation(q), carrier[..., 4:7])
    return jnp.concatenate([q_dot, t_dot, carrier[..., 7:]], axis=-1)


def carrier_from_raw(params, params_dot):
    r"""The carrier of a raw derivative: $(\rho, \omega)$ as in SO3, $v = R^\top \dot t / s$, $\dot\sigma$."""
    q, sigma = params[..., :4], params[..., 7:]
    rotational = so3.carrier_from_raw(q, params_dot[..., :4])
    v = rotate_back(so3.unit_rotation(q), params_dot[..., 4:7]) * jnp.exp(-sigma)
    return jnp.concatenate([rotational, v, params_dot[..., 7:]], axis=-1)


@jax.custom_jvp
def join(q, t, sigma):
    """Sim3 parameters from SO3 parameters, a raw translation and a raw log-scale `(*batch, 1)`."""
    return _join(q, t, sigma)


@join.defjvp
def _join_jvp(primals, tangents):
    r"""The rotation's carrier passes through; $v = R^\top \dot t / s$; $\dot\sigma$ passes through."""
    (q, t, sigma), (q_carrier, t_dot, sigma_dot) = primals, tangents
    params = join(q, t, sigma)
    v = rotate_back(so3.as_matrix(q), t_dot) * jnp.exp(-sigma)
    return params, _join(q_carrier, v, sigma_dot)


def _components(params):
    """$R$, $t$ and $s$ for use inside rules (through kernels, so that rules differentiate correctly)."""
    raw = to_parameters(params)
    return so3.as_matrix(params[..., :4]), raw[..., 4:7], jnp.exp(raw[..., 7:])


# ---- the Lie algebra and the Jacobians of Exp -----------------------------------------------------


def hat(xi):
    r"""$\xi^\wedge = [[\omega]_\times + \sigma I, v; 0, 0]$."""
    linear = skew(xi[..., 3:6]) + xi[..., 6:, None] * jnp.eye(3, dtype=xi.dtype)
    top = jnp.concatenate([linear, xi[..., :3, None]], axis=-1)
    return jnp.concatenate([top, jnp.zeros_like(top[..., :1, :])], axis=-2)


def vee(matrix):
    r"""$(v, \omega, \sigma)$ of an algebra matrix: $\sigma$ is a third of the trace of the linear block."""
    linear = matrix[..., :3, :3]
    trace = linear[..., 0, 0] + linear[..., 1, 1] + linear[..., 2, 2]
    return jnp.concatenate([matrix[..., :3, 3], unskew(linear), trace[..., None] / 3.0], axis=-1)


def ad(xi):
    r"""$\mathrm{ad}_\xi = [[[\omega]_\times + \sigma I, [v]_\times, -v], [0, [\omega]_\times, 0],
    [0, 0, 0]]$, with $[\xi^\wedge, \eta^\wedge] = (\mathrm{ad}_\xi \eta)^\wedge$."""
    v, omega, sigma = xi[..., :3], xi[..., 3:6], xi[..., 6:]
    w = skew(omega)
    eye = jnp.eye(3, dtype=xi.dtype)
    zero33, zero31 = jnp.zeros_like(w), jnp.zeros_like(v[..., None])
    zero13 = jnp.zeros_like(v[..., None, :])
    zero11 = jnp.zeros_like(sigma[..., None])
    return blocks(
        [
            [w + sigma[..., None] * eye, skew(v), -v[..., None]],
            [zero33, w, zero31],
            [zero13, zero13, zero11],
        ]
    )


_PHI_TERMS = 16  # Taylor terms of φ₁ after scaling to norm ≤ 1/2: error < 0.5¹⁷/18! ≈ 1e-21
_MAX_DOUBLINGS = 12  # accurate for ‖ad_ξ‖∞ up to 2¹¹ (e.g. translations of a few hundred units)


def phi1_matrix(matrix):
    r"""$\varphi_1(X) = \sum_k X^k / (k + 1)!$ by scaling and doubling: $Y = X / 2^j$ with
    $\|Y\|_\infty \le 1/2$, the Taylor polynomial of $\varphi_1(Y)$, then $j$ times
    $\varphi_1(2Y) = \tfrac12 \varphi_1(Y)(e^Y + I) = \varphi_1(Y) + \tfrac12 \varphi_1(Y)\,Y\,\varphi_1(Y)$
    (from $e^Y = I + Y\varphi_1(Y)$). The number of doublings depends on the data but the loop is
    unrolled to `_MAX_DOUBLINGS` masked steps, so the function is differentiable in every mode
    (no `cond`, no `while_loop`) and NaN-free at $X = 0$."""
    n = matrix.shape[-1]
    eye = jnp.eye(n, dtype=matrix.dtype)
    norm = jax.lax.stop_gradient(jnp.max(jnp.sum(jnp.abs(matrix), axis=-1), axis=-1))
    doublings = jnp.clip(jnp.ceil(jnp.log2(jnp.maximum(norm, 1e-300) / 0.5)), 0, _MAX_DOUBLINGS)
    scaled = matrix * jnp.exp2(-doublings)[..., None, None]
    phi = eye + scaled / (_PHI_TERMS + 1)
    for k in range(_PHI_TERMS - 1, 0, -1):
        phi = eye + (scaled @ phi) / (k + 1)
    for step in range(_MAX_DOUBLINGS):
        doubled = phi + 0.5 * (phi @ (scaled @ phi))
        active = (step < doublings)[..., None, None]
        phi = jnp.where(active, doubled, phi)
        scaled = jnp.where(active, 2.0 * scaled, scaled)
    return phi


def right_jacobian(xi):
    r"""$J_r(\xi) = \varphi_1(-\mathrm{ad}_\xi)$ (see the module docstring and `phi1_matrix`)."""
    return phi1_matrix(-ad(xi))


def right_jacobian_inverse(xi):
    r"""$J_r(\xi)^{-1}$ (the inverse of `right_jacobian`)."""
    return jnp.linalg.inv(right_jacobian(xi))


# ---- kernels with closed-form rules -------------------------------------------------------------


def _exp(xi):
    r"""$\mathrm{Exp}(v, \omega, \sigma) = (\mathrm{Exp}(\omega),\ W(\sigma, \omega)\,v,\ \sigma)$."""
    v, omega, sigma = xi[..., :3], xi[..., 3:6], xi[..., 6:]
    return jnp.concatenate([so3.exp(omega), apply_w(sigma[..., 0], omega, v), sigma], axis=-1)


def _log(params):
    r"""$\mathrm{Log}(T) = (W(\sigma, \omega)^{-1} t,\ \omega,\ \sigma)$, $\omega = \mathrm{Log}(q)$."""
    q, t, sigma = _split(params)
    omega = so3.log(q)
    v = _solve3(w_matrix(sigma[..., 0], omega), t)
    return jnp.concatenate([v, omega, sigma], axis=-1)


@jax.custom_jvp
def compose(params1, params2):
    r"""$T_1 T_2 = (q_1 \otimes q_2,\ s_1 R_1 t_2 + t_1,\ \sigma_1 + \sigma_2)$."""
    q1, t1, sigma1 = _split(params1)
    q2, t2, sigma2 = _split(params2)
    t = jnp.exp(sigma1) * quat_rotate(q1, t2) + t1
    return _join(quat_multiply(q1, q2), t, sigma1 + sigma2)


@_rules.defjvp(compose)
def _compose_jvp(primals, tangents):
    r"""Local block: $\xi = \mathrm{Ad}(T_2^{-1})\,\xi_1 + \xi_2$, i.e.
    $v = R_2^\top(v_1 + \omega_1 \times t_2 + \sigma_1 t_2)/s_2 + v_2$,
    $\omega = R_2^\top \omega_1 + \omega_2$, $\sigma = \sigma_1 + \sigma_2$."""
    (params1, params2), (params1_dot, params2_dot) = primals, tangents
    params = compose(params1, params2)
    xi1 = _rules.local_tangent(to_local, params1, params1_dot)
    xi2 = _rules.local_tangent(to_local, params2, params2_dot)
    moved = None
    if xi1 is not None:
        rotation2, t2, s2 = _components(params2)
        v1, omega1, sigma1 = xi1[..., :3], xi1[..., 3:6], xi1[..., 6:]
        v = rotate_back(rotation2, v1 + cross(omega1, t2) + sigma1 * t2) / s2
        # a single T1 composed with a batch of T2: σ1 takes the batch shape of v and ω
        sigma1 = jnp.broadcast_to(sigma1, (*v.shape[:-1], 1))
        moved = jnp.concatenate([v, rotate_back(rotation2, omega1), sigma1], axis=-1)
    xi = _rules.add(moved, xi2)
    return _rules.finish(params, None if xi is None else from_local(params, xi))


@jax.custom_jvp
def inverse(params):
    r"""$T^{-1} = (\bar q,\ -R^\top t / s,\ -\sigma)$."""
    q, t, sigma = _split(params)
    q_inverse = quat_conjugate(q)
    return jnp.concatenate(
        [q_inverse, -jnp.exp(-sigma) * quat_rotate(q_inverse, t), -sigma], axis=-1
    )


@inverse.defjvp
def _inverse_jvp(primals, tangents):
    r"""Local block $-\mathrm{Ad}(T)$: $\omega' = -R\omega$, $\sigma' = -\sigma$,
    $v' = -(s R v + t \times R\omega - \sigma t)$."""
    (params,), (params_dot,) = primals, tangents
    params_inverse = inverse(params)
    rotation, t, s = _components(params)
    xi = to_local(params, params_dot)
    v, omega, sigma = xi[..., :3], xi[..., 3:6], xi[..., 6:]
    rotated_omega = matvec(rotation, omega)
    v_out = s * matvec(rotation, v) + cross(t, rotated_omega) - sigma * t
    xi_out = -jnp.concatenate([v_out, rotated_omega, sigma], axis=-1)
    return params_inverse, from_local(params_inverse, xi_out)


@jax.custom_jvp
def act(params, points):
    """$T p = s R p + t$."""
    q, t, sigma = _split(params)
    return jnp.exp(sigma) * matvec(quat_to_matrix(q), points) + t


@_rules.defjvp(act)
def _act_jvp(primals, tangents):
    r"""$\dot y = s R (v + \omega \times p + \sigma p + \dot p)$: blocks
    $[sR, -sR[p]_\times, sRp]$ and $sR$."""
    (params, points), (params_dot, points_dot) = primals, tangents
    moved = act(params, points)
    xi = _rules.local_tangent(to_local, params, params_dot)
    direction = _rules.add(
        None if xi is None else xi[..., :3] + cross(xi[..., 3:6], points) + xi[..., 6:] * points,
        None if _rules.is_zero(points_dot) else points_dot,
    )
    if direction is None:
        return _rules.finish(moved, None)
    rotation, _, s = _components(params)
    return _rules.finish(moved, s * matvec(rotation, direction))


def _adjoint(params):
    r"""$\mathrm{Ad}_T = [[sR, [t]_\times R, -t], [0, R, 0], [0, 0, 1]]$ (tangent $(v, \omega, \sigma)$)."""
    q, t, sigma = _split(params)
    rotation = quat_to_matrix(q)
    s = jnp.exp(sigma)[..., None]
    zero33 = jnp.zeros_like(rotation)
    zero31 = jnp.zeros_like(t[..., None])
    zero13 = jnp.zeros_like(t[..., None, :])
    one = jnp.ones_like(sigma[..., None])
    return blocks(
        [
            [s * rotation, skew(t) @ rotation, -t[..., None]],
            [zero33, rotation, zero31],
            [zero13, zero13, one],
        ]
    )


def _as_matrix(params):
    """$T = [s R(q), t; 0, 1]$."""
    q, t, sigma = _split(params)
    linear = jnp.exp(sigma)[..., None] * quat_to_matrix(q)
    top = jnp.concatenate([linear, t[..., None]], axis=-1)
    bottom = jnp.broadcast_to(
        jnp.array([0.0, 0.0, 0.0, 1.0], dtype=params.dtype), top[..., :1, :].shape
    )
    return jnp.concatenate([top, bottom], axis=-2)


def _scale_of(linear):
    r"""$s = \det(sR)^{1/3}$."""
    return jnp.cbrt(jnp.linalg.det(linear))


def _from_matrix(matrix):
    r"""$s = \det(M_{3\times3})^{1/3}$, the rotation by `SO3.from_matrix(M/s)` (re-orthogonalized),
    the translation the last column."""
    linear = matrix[..., :3, :3]
    s = _scale_of(linear)
    q = so3.from_matrix(linear / s[..., None, None])
    return _join(q, matrix[..., :3, 3], jnp.log(s)[..., None])


def _normalize(params):
    """Unit quaternion; translation and log-scale unchanged."""
    q, t, sigma = _split(params)
    return jnp.concatenate([so3.normalize(q), t, sigma], axis=-1)


# The generic rules (lieax.groups._generic) for all but compose, inverse and act, whose closed
# forms above avoid the 7×7 adjoint.
_ops = _generic.local_rules(
    sys.modules[__name__], exp=_exp, log=_log, compose=compose, inverse=inverse,
    adjoint=_adjoint, as_matrix=_as_matrix, from_matrix=_from_matrix, normalize=_normalize,
)  # fmt: skip
exp, log, adjoint, as_matrix = _ops.exp, _ops.log, _ops.adjoint, _ops.as_matrix
from_matrix, normalize = _ops.from_matrix, _ops.normalize
to_parameters, from_parameters = _ops.to_parameters, _ops.from_parameters


def sample_uniform(key, batch_shape, dtype):
    """Uniform rotation (Haar), translation uniform in $[-1, 1]^3$, log-scale uniform in $[-1, 1]$."""
    key_rotation, key_translation, key_scale = jax.random.split(key, 3)
    q = so3.sample_uniform(key_rotation, batch_shape, dtype)
    t = jax.random.uniform(
        key_translation, (*batch_shape, 3), dtype=q.dtype, minval=-1.0, maxval=1.0
    )
    sigma = jax.random.uniform(key_scale, (*batch_shape, 1), dtype=q.dtype, minval=-1.0, maxval=1.0)
    return jnp.concatenate([q, t, sigma], axis=-1)


class _RotationAndTranslation(Protocol):
    """What `Sim3.from_se3` reads of its pose: an `SE3` (which this module cannot import, as
    `_se3` imports it), or anything with an `SO3` rotation and a translation."""

    def rotation(self) -> SO3: ...

    def translation(self) -> jax.Array: ...


class Sim3(AbstractGroup):
    r"""Similarity transforms in 3D: parameters `(w, x, y, z, tx, ty, tz, σ)`, shape `(*batch, 8)`,
    with scale $s = e^\sigma$; tangent `(vx, vy, vz, ωx, ωy, ωz, σ)`, shape `(*batch, 7)`;
    $T p = s R p + t$."""

    tangent_dim = 7
    parameters_dim = 8
    space_dim = 3
    matrix_dim = 4
    parameters_layout = "quaternion wxyz, then translation xyz, then log-scale σ"

    @property
    def wxyz_xyz_log_scale(self) -> jax.Array:
        return self.parameters()

    @classmethod
    def from_rotation_translation_scale(
        cls, rotation: SO3, translation: ArrayLike, scale: ArrayLike = 1.0
    ) -> Self:
        r"""$T = [sR, t; 0, 1]$ from an `SO3`, a translation `(*batch, 3)` and a positive scale
        `(*batch)`, broadcasting batch shapes (stored as $\sigma = \log s$); a translation or scale
        that states no dtype (a Python or NumPy number) takes the rotation's.

        A concrete scale that is not positive and finite is a `ValueError`; a traced one (under
        `jit`) cannot be checked, and a nonpositive value there gives a NaN (or $-\infty$)
        log-scale that propagates to every result."""
        name = "Sim3.from_rotation_translation_scale"
        if not isinstance(rotation, SO3):
            raise TypeError(f"rotation must be an SO3, got {type(rotation).__name__}.")
        translation = match_dtype(
            translation, rotation.dtype, f"{name} translation", "the rotation"
        )
        translation = check_last_axis(translation, 3, f"{name} translation")
        scale = match_dtype(scale, rotation.dtype, f"{name} scale", "the rotation")
        check_positive(scale, f"{name} scale")
        broadcast_batch(name, rotation.batch_shape, translation.shape[:-1], scale.shape)
        return cls._wrap(join(rotation._params, translation, jnp.log(scale)[..., None]))

    @classmethod
    def from_se3(cls, pose: _RotationAndTranslation, scale: ArrayLike = 1.0) -> Self:
        """The similarity with the rotation and translation of an `SE3` and the given scale."""
        return cls.from_rotation_translation_scale(pose.rotation(), pose.translation(), scale)

    @classmethod
    def from_scale(cls, scale: ArrayLike) -> Self:
        """A pure scaling about the origin by positive scales of shape `(*batch)` (checked as in
        `from_rotation_translation_scale`)."""
        scale = as_float_array(scale, "Sim3.from_scale scale")
        check_positive(scale, "Sim3.from_scale scale")
        return cls.from_rotation_translation_scale(
            SO3.identity(scale.shape, dtype=scale.dtype),
            jnp.zeros((*scale.shape, 3), scale.dtype),
            scale,
        )

    @classmethod
    def align(
        cls, points_a: ArrayLike, points_b: ArrayLike, weights: ArrayLike | None = None
    ) -> Self:
        r"""The similarity $T_{ab}$ minimizing $\sum_i w_i |a_i - T_{ab} b_i|^2$ (Umeyama); see
        `lieax.align` and `lieax.groups._procrustes`."""
        q, t, sigma = _procrustes.solve(
            points_a, points_b, weights, with_scale=True, what="Sim3.align"
        )
        return cls._wrap(join(q, t, sigma[..., None]))

    def rotation(self) -> SO3:
        return SO3._wrap(self._params[..., :4])

    def translation(self) -> jax.Array:
        return self.parameters()[..., 4:7]

    def log_scale(self) -> jax.Array:
        r"""$\sigma$, shape `(*batch)`."""
        return self.parameters()[..., 7]

    def scale(self) -> jax.Array:
        r"""$s = e^\sigma$, shape `(*batch)`."""
        return jnp.exp(self.log_scale())
