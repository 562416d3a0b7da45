r"""One interval preintegrated by a sequential `lax.scan` on 3×3 blocks, exactly GTSAM's
`TangentPreintegration::update` and `PreintegratedImuMeasurements::integrateMeasurement`
(Forster et al., T-RO 2017): the step's kinematics and Jacobians (`_kinematics`, shared with
`preintegrate_combined`), the covariance propagated on its six upper blocks (`_propagate`) and the
bias Jacobian (`_tangent_step`), and the scan (`_block_scan`). Conventions: docs/conventions.md.
"""

from typing import NamedTuple

import jax
import jax.numpy as jnp

from .._linalg import cross, skew
from ..groups import kernels
from ._samples import _corrected, _scanned


def _so3_at(theta, omega):
    r"""$R = \mathrm{Exp}(\theta) = I + g_1 W + g_2 W^2$, $J_r = I - g_2 W + g_3 W^2$,
    $J_r^{-1} = I + \tfrac12 W + D W^2$ ($W = [\theta]_\times$, $W^2 = \theta\theta^\top -
    \theta^2 I$; Solà eqs. 77, 143, 144) and $\partial(J_r^{-1}(\theta)\omega)/\partial\theta =
    -\tfrac12[\omega]_\times + D\,((\theta\cdot\omega) I + \theta\omega^\top - 2\omega\theta^\top)
    + 2D'(s)\,\theta\times(\theta\times\omega)\,\theta^\top$ (GTSAM's `DexpFunctor`, its
    `applyInvDexp` derivative), all from one cosine and one sine of $\theta/2$
    (`lieax.groups._so3.exp_coefficients`, `jr_inverse_coefficients`). Returns
    $(R, J_r, J_r^{-1}, J_r^{-1}\omega, \partial(J_r^{-1}\omega)/\partial\theta)$."""
    s = jnp.dot(theta, theta)
    eye = jnp.eye(3, dtype=theta.dtype)
    w = skew(theta)
    w2 = jnp.outer(theta, theta) - s * eye
    half_cos, half_sinc, g1, g2, g3 = kernels.so3_exp_coefficients(s)
    d, d_prime = kernels.so3_jr_inverse_coefficients(s, half_cos, half_sinc)
    rotation = eye + g1 * w + g2 * w2
    jr = eye - g2 * w + g3 * w2
    jr_inv = eye + 0.5 * w + d * w2
    u = cross(theta, cross(theta, omega))
    h = (
        -0.5 * skew(omega)
        + d
        * (jnp.dot(theta, omega) * eye + jnp.outer(theta, omega) - 2.0 * jnp.outer(omega, theta))
        + 2.0 * d_prime * jnp.outer(u, theta)
    )
    return rotation, jr, jr_inv, jr_inv @ omega, h


class _Step(NamedTuple):
    r"""The blocks of one step's Jacobians (`_kinematics`): $A_{\theta\theta}$ (`a00`),
    $A_{p\theta}$ (`a10`; $A_{v\theta} = k A_{p\theta}$, $k = 2/\delta t$), the sample Jacobians
    $C_\theta = \partial\theta^+/\partial\tilde\omega$ (`c_w`), $B_p = \partial p^+/\partial\tilde a$
    (`p_a`; $B_v = k B_p$) and $\partial p^+/\partial\tilde\omega$ (`p_w`, the lever arm's
    coupling, `None` without a sensor pose), and `dt`, `k`."""

    a00: jax.Array
    a10: jax.Array
    c_w: jax.Array
    p_a: jax.Array
    p_w: jax.Array | None
    dt: jax.Array
    k: jax.Array


def _kinematics(x, sample, bias, params):
    r"""One `TangentPreintegration::update`: $\theta^+ = \theta + J_r^{-1}(\theta)\omega\delta t$,
    $p^+ = p + v\delta t + \tfrac12 R a \delta t^2$, $v^+ = v + R a \delta t$ with
    $R = \mathrm{Exp}(\theta)$ before the update, and its Jacobians (`_Step`):
    $A = [[I + \partial_\theta(J_r^{-1}\omega)\delta t, 0, 0], [H\tfrac{\delta t^2}2, I, I\delta t],
    [H\delta t, 0, I]]$, $H = -R[a]_\times J_r(\theta)$, $B = [0; R\tfrac{\delta t^2}2; R\delta t]$,
    $C = [J_r^{-1}(\theta)\delta t; 0; 0]$ (with respect to the raw samples: times the
    sensor-pose correction's Jacobians)."""
    gyro, accel, dt = sample
    acc, omega, d = _corrected(accel, gyro, bias, params)
    theta, p, v = x[:3], x[3:6], x[6:]
    rotation, jr, jr_inv, w_tangent, w_tangent_H_theta = _so3_at(theta, omega)
    a00 = jnp.eye(3, dtype=x.dtype) + dt * w_tangent_H_theta
    a_nav = rotation @ acc
    dt22, k = 0.5 * dt * dt, 2.0 / dt
    x_next = jnp.concatenate([theta + w_tangent * dt, p + v * dt + a_nav * dt22, v + a_nav * dt])
    a10 = (rotation @ skew(-acc) @ jr) * dt22  # a20 = k * a10
    c_w = jr_inv * dt
    p_a, p_w = rotation * dt22, None
    if d is not None:
        d_aa, d_aw, d_ww = d
        p_a, p_w, c_w = p_a @ d_aa, p_a @ d_aw, c_w @ d_ww
    return x_next, _Step(a00, a10, c_w, p_a, p_w, dt, k)


def _times_a(step, rows):
    r"""$A M$ for a $9 \times n$ matrix $M$ given as its row blocks $(M_\theta, M_p, M_v)$."""
    m_t, m_p, m_v = rows
    a10_m = step.a10 @ m_t
    return step.a00 @ m_t, a10_m + m_p + step.dt * m_v, step.k * a10_m + m_v


def _propagate(s, step, q_tt, q_tp, q_pp, integration):
    r"""$A \Sigma A^\top + Q$ on the six upper 3×3 blocks `(θθ, θp, θv, pp, pv, vv)` of $\Sigma$,
    for noise entering through the θ and p rows (the v rows are $k$ times the p rows):
    $Q_{\theta\theta}$, $Q_{\theta p}$, $Q_{pp}$ given, $Q_{\theta v} = k Q_{\theta p}$,
    $Q_{pv} = k Q_{pp}$, $Q_{vv} = k^2 Q_{pp}$, and `integration` added to the pp block only.
    $X = A\Sigma$ first (its θ row blocks, the θ and v columns of its v rows), then $X A^\top$."""
    tt, tp, tv, pp, pv, vv = s
    a00, a10, dt, k = step.a00, step.a10, step.dt, step.k
    x_t = (a00 @ tt, a00 @ tp, a00 @ tv)
    m = (a10 @ tt, a10 @ tp, a10 @ tv)
    x_p = (m[0] + tp.T + dt * tv.T, m[1] + pp + dt * pv.T, m[2] + pv + dt * vv)
    x_v = (k * m[0] + tv.T, k * m[2] + vv)  # the θ and v column blocks (p is not needed)
    a10t = a10.T
    return (
        x_t[0] @ a00.T + q_tt,
        x_t[0] @ a10t + x_t[1] + dt * x_t[2] + q_tp,
        k * (x_t[0] @ a10t) + x_t[2] + k * q_tp,
        x_p[0] @ a10t + x_p[1] + dt * x_p[2] + q_pp + integration,
        k * (x_p[0] @ a10t) + x_p[2] + k * q_pp,
        k * (x_v[0] @ a10t) + x_v[1] + k * k * q_pp,
    )


def _tangent_step(carry, sample, bias, params):
    r"""One `PreintegratedImuMeasurements::integrateMeasurement` (`_kinematics`):
    $\Sigma^+ = A\Sigma A^\top + B\frac{\Sigma_a}{\delta t}B^\top + C\frac{\Sigma_g}{\delta t}C^\top
    + \Sigma_i\delta t$ (position block), $J_b^+ = A J_b - [B, C]$, evaluated on 3×3 blocks
    (`_propagate`). The covariance `s` is its six upper blocks `(θθ, θp, θv, pp, pv, vv)`, the
    bias Jacobian `j` its three row blocks."""
    x, s, j = carry
    x_next, step = _kinematics(x, sample, bias, params)
    c_w, p_a, p_w, dt, k = step.c_w, step.p_a, step.p_w, step.dt, step.k
    sa = params.accelerometer_covariance / dt
    sg = params.gyroscope_covariance / dt
    q_tt = c_w @ sg @ c_w.T
    q_tp = 0.0 if p_w is None else c_w @ sg @ p_w.T
    q_pp = p_a @ sa @ p_a.T + (0.0 if p_w is None else p_w @ sg @ p_w.T)
    s_next = _propagate(s, step, q_tt, q_tp, q_pp, params.integration_covariance * dt)
    zero = jnp.zeros_like(c_w)
    bc_t = jnp.concatenate([zero, c_w], axis=1)
    bc_p = jnp.concatenate([p_a, zero if p_w is None else p_w], axis=1)
    j_t, j_p, j_v = _times_a(step, j)
    return (x_next, s_next, (j_t - bc_t, j_p - bc_p, j_v - k * bc_p)), None


def _block_scan(gyro, accel, dt, bias, params, keep):
    """`_tangent_step` (3×3 blocks) over the samples of one interval (those `keep` holds,
    `_masked`): `(x, covariance, jacobian_bias)`."""
    dtype = gyro.dtype
    zero = jnp.zeros((3, 3), dtype)
    init = (jnp.zeros(9, dtype), (zero,) * 6, (jnp.zeros((3, 6), dtype),) * 3)
    x, s, j = _scanned(
        lambda carry, sample: _tangent_step(carry, sample, bias, params),
        init,
        keep,
        gyro,
        accel,
        dt,
    )
    return x, _covariance(s), jnp.concatenate(j)


def _covariance(s):
    """The symmetric 9×9 covariance from its six upper 3×3 blocks `(θθ, θp, θv, pp, pv, vv)`."""
    tt, tp, tv, pp, pv, vv = s
    return jnp.block([[tt, tp, tv], [tp.T, pp, pv], [tv.T, pv.T, vv]])
