r"""`preintegrate_combined`: one interval with GTSAM 4.3's `PreintegratedCombinedMeasurements`
covariance, the 15×15 covariance of the increments and the biases propagated with the biases'
random walk (`BiasRandomWalk`), by a sequential `lax.scan` over `_block_scan`'s step kinematics.
"""

import jax
import jax.numpy as jnp

from ._block_scan import _covariance, _kinematics, _propagate, _times_a
from ._params import BiasRandomWalk, ImuError, ImuParams
from ._preintegrated import _result
from ._samples import _check_samples, _delta_t, _samples_by_keyword, _scanned


def _combined_step(carry, sample, bias, params, walk):
    r"""One `PreintegratedCombinedMeasurements::integrateMeasurement` (GTSAM 4.3): the 15×15
    covariance of $(\theta, \Delta p, \Delta v, b_a, b_g)$, $\Sigma^+ = F \Sigma F^\top + Q$ with
    $F = [[A, F_b], [0, I]]$, $F_b = [B, C]$ (`_kinematics`, the sample Jacobians: a bias moves
    the increments as the samples do) and $Q = \mathrm{diag}(Q_{nav}, \Sigma_{b_a}\delta t,
    \Sigma_{b_g}\delta t)$, $Q_{nav}$ `_tangent_step`'s. In blocks, with $\Sigma = [[P, X],
    [X^\top, S]]$: $P^+ = A P A^\top + W F_b^\top + F_b W^\top + Q_{nav}$, $W = A X + \tfrac12 F_b
    S$, $X^+ = A X + F_b S$, $S^+ = S + \mathrm{diag}(\Sigma_{b_a}, \Sigma_{b_g})\delta t$.
    `cross_nb` is $X$'s three row blocks (3×6), `s_bb` is $S$."""
    x, s, j, cross_nb, s_bb = carry
    x_next, step = _kinematics(x, sample, bias, params)
    c_w, p_a, p_w, dt, k = step.c_w, step.p_a, step.p_w, step.dt, step.k
    zero = jnp.zeros_like(c_w)
    p_w = zero if p_w is None else p_w
    sg = params.gyroscope_covariance / dt
    q_tt = c_w @ sg @ c_w.T
    q_tp = c_w @ sg @ p_w.T
    q_pp = p_a @ (params.accelerometer_covariance / dt) @ p_a.T + p_w @ sg @ p_w.T
    s_next = _propagate(s, step, q_tt, q_tp, q_pp, params.integration_covariance * dt)
    fb_t = jnp.concatenate([zero, c_w], axis=1)
    fb_p = jnp.concatenate([p_a, p_w], axis=1)
    fb_s = (fb_t @ s_bb, fb_p @ s_bb, k * (fb_p @ s_bb))
    a_x = _times_a(step, cross_nb)
    w_t, w_p, w_v = (a + 0.5 * f for a, f in zip(a_x, fb_s))
    # M(r, c) = W_r F_b,cᵀ; the v columns are k times the p columns.
    m_tt, m_tp = w_t @ fb_t.T, w_t @ fb_p.T
    m_pt, m_pp = w_p @ fb_t.T, w_p @ fb_p.T
    m_vt, m_vp = w_v @ fb_t.T, w_v @ fb_p.T
    tt, tp, tv, pp, pv, vv = s_next
    s_next = (
        tt + m_tt + m_tt.T,
        tp + m_tp + m_pt.T,
        tv + k * m_tp + m_vt.T,
        pp + m_pp + m_pp.T,
        pv + k * m_pp + m_vp.T,
        vv + k * (m_vp + m_vp.T),
    )
    cross_next = tuple(a + f for a, f in zip(a_x, fb_s))
    walk_q = jax.scipy.linalg.block_diag(
        walk.accelerometer_bias_covariance, walk.gyroscope_bias_covariance
    )
    j_t, j_p, j_v = _times_a(step, j)
    j_next = (j_t - fb_t, j_p - fb_p, j_v - k * fb_p)
    return (x_next, s_next, j_next, cross_next, s_bb + walk_q * dt), None


@_samples_by_keyword
def preintegrate_combined(
    params: ImuParams, walk: BiasRandomWalk, bias=None, *, accel, gyro, dt, mask=None
):
    r"""`preintegrate` with GTSAM 4.3's `PreintegratedCombinedMeasurements` covariance: the
    15×15 covariance of $(\theta, \Delta p, \Delta v, b_a, b_g)$ propagated with the biases'
    random walk `walk` and their coupling into the increments (`_combined_step`; its
    `preintMeasCov()`, which GTSAM's `CombinedImuFactor` whitens its 15-vector residual with).
    Same arguments as `preintegrate`, plus `walk` (a `BiasRandomWalk`, GTSAM's
    `PreintegrationCombinedParams`' bias covariances).

    **Returns:** `(pim, covariance)`: a `Preintegrated` whose increments and bias Jacobians are
    `preintegrate`'s and whose `covariance` is the 9×9 navigation block of `covariance`
    `(15, 15)` (`preintegrate`'s plus the random walk's share; equal to it for a zero walk).
    `vmap` it over intervals.
    """
    gyro, accel, dt, bias, keep, ok = _check_samples(gyro, accel, dt, bias, params, mask)
    if not isinstance(walk, BiasRandomWalk):
        raise TypeError(f"walk must be a BiasRandomWalk, got {type(walk).__name__}.")
    for name, value in zip(walk._fields, walk):
        if jnp.shape(value) != (3, 3):
            raise ImuError(f"walk.{name} must be (3, 3), got {jnp.shape(value)}.")
    dtype = gyro.dtype
    zero, zero36 = jnp.zeros((3, 3), dtype), jnp.zeros((3, 6), dtype)
    init = (
        jnp.zeros(9, dtype),
        (zero,) * 6,
        (zero36,) * 3,
        (zero36,) * 3,
        jnp.zeros((6, 6), dtype),
    )
    x, s, j, cross_nb, s_bb = _scanned(
        lambda carry, sample: _combined_step(carry, sample, bias, params, walk),
        init,
        keep,
        gyro,
        accel,
        dt,
    )
    nav = _covariance(s)
    x_nb = jnp.concatenate(cross_nb)
    covariance = jnp.block([[nav, x_nb], [x_nb.T, s_bb]])
    pim = _result(x, _delta_t(dt, keep), nav, jnp.concatenate(j), bias, ok)
    return pim, jnp.where(ok, covariance, jnp.nan)
