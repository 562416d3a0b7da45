r"""One interval preintegrated by the sequential scan of `_block_scan`, written on scalar
entries (`_entry_step`), so that under `vmap` every operation is elementwise over the intervals:
`vmap(preintegrate)` over a batch of many samples runs it (`_sequential._dispatch_batched`).
GTSAM's `TangentPreintegration::update`; Forster et al., T-RO 2017.
"""

import jax
import jax.numpy as jnp
import numpy as np

from ..groups import kernels
from ._block_scan import _covariance
from ._samples import _corrected, _scanned

_UPPER = ((0, 0), (0, 1), (0, 2), (1, 1), (1, 2), (2, 2))  # a symmetric 3×3 block's entries


def _entries(m):
    """A `(..., 3, 3)` array as nested tuples of its entries."""
    return tuple(tuple(m[..., i, j] for j in range(3)) for i in range(3))


def _stacked(m):
    """Nested tuples of entries (3×3) as an array."""
    return jnp.stack([jnp.stack(row) for row in m])


def _sum(*ms):
    """The entrywise sum of nested entries."""
    return jax.tree.map(lambda *xs: sum(xs[1:], xs[0]), *ms)


def _scaled(c, m):
    """Nested entries times `c`."""
    return jax.tree.map(lambda x: c * x, m)


def _t(m):
    """The transpose of nested 3×3 entries."""
    return tuple(tuple(m[j][i] for j in range(3)) for i in range(3))


def _mm(a, b):
    r"""$a b$ of nested 3×3 entries."""
    return tuple(
        tuple(a[i][0] * b[0][j] + a[i][1] * b[1][j] + a[i][2] * b[2][j] for j in range(3))
        for i in range(3)
    )


def _mmt(a, b, upper=False):
    r"""$a b^\top$ of nested 3×3 entries, or its upper triangle (`_UPPER`) for a symmetric one."""
    pairs = _UPPER if upper else tuple((i, j) for i in range(3) for j in range(3))
    out = tuple(a[i][0] * b[j][0] + a[i][1] * b[j][1] + a[i][2] * b[j][2] for i, j in pairs)
    return out if upper else (out[0:3], out[3:6], out[6:9])


def _full(upper):
    """The symmetric 3×3 entries from the upper triangle (`_UPPER` order)."""
    index = {pair: n for n, pair in enumerate(_UPPER)}
    return tuple(tuple(upper[index[min(i, j), max(i, j)]] for j in range(3)) for i in range(3))


def _upper(m):
    """The upper triangle (`_UPPER` order) of nested 3×3 entries."""
    return tuple(m[i][j] for i, j in _UPPER)


def _materialize(tree):
    r"""`tree`'s values, computed once. XLA's CPU fusion copies cheap elementwise producers into
    every consumer, so a step written entry by entry would recompute most of its graph for each
    of the ~100 entries of the carry (measured: 23k fused instructions per step instead of 7.6k,
    2.5× slower than the 3×3 products); a gather is an operation it does not duplicate (its
    `IsExpensive`), so the values go through one stack and gather (a reversal) and each is
    stored once. The values are unchanged (a later XLA that duplicated gathers would change the
    speed only); `jax.lax.optimization_barrier` does not help (XLA removes it before fusion)."""
    leaves, treedef = jax.tree.flatten(tree)
    n = len(leaves)
    stacked = jnp.stack(leaves)[np.arange(n)[::-1]]
    return jax.tree.unflatten(treedef, [stacked[n - 1 - i] for i in range(n)])


def _entry_step(carry, sample, noise, d_aa):
    r"""One `PreintegratedImuMeasurements::integrateMeasurement`, `_tangent_step`'s update
    written on scalar entries, so that under `vmap` every operation is elementwise over the
    intervals: with $R = \mathrm{Exp}(\theta)$,
    $J_r$, $J_r^{-1}$ and $H = \partial(J_r^{-1}(\theta)\omega)/\partial\theta$ of `_so3_at`,
    $\theta^+ = \theta + J_r^{-1}\omega\delta t$, $p^+ = p + v\delta t + \tfrac12 R a\delta t^2$,
    $v^+ = v + R a\delta t$;
    $\Sigma^+ = A\Sigma A^\top + B\frac{\Sigma_a}{\delta t}B^\top + C\frac{\Sigma_g}{\delta t}
    C^\top + \Sigma_i\delta t$ (position block), $J_b^+ = A J_b - [B, C]$ with
    $A = [[I + H\delta t, 0, 0], [A_{p\theta}, I, I\delta t], [k A_{p\theta}, 0, I]]$,
    $A_{p\theta} = -R[a]_\times J_r\tfrac{\delta t^2}2$, $k = 2/\delta t$,
    $B = [0; R\tfrac{\delta t^2}2; R\delta t]\,\partial a/\partial\tilde a$ and
    $C = [J_r^{-1}\delta t; 0; 0]\,\partial\omega/\partial\tilde\omega$, plus the lever arm's
    $\partial p^+/\partial\tilde\omega$ (GTSAM's `TangentPreintegration::update`; Forster et al.
    2017). The step's kinematics (`_entry_kinematics`), covariance (`_entry_covariance`) and
    bias Jacobian (`_entry_bias_jacobian`) are three functions.

    The covariance is its six upper blocks `(θθ, θp, θv, pp, pv, vv)` (the diagonal ones as
    upper triangles), the bias Jacobian its blocks `(θ/b_g, (p/b_a, p/b_g), (v/b_a, v/b_g))`
    ($\partial\theta/\partial b_a = 0$); `noise` is $(\Sigma_a, \Sigma_g, \Sigma_i)$ and `d_aa`
    $\partial a/\partial\tilde a = \partial\omega/\partial\tilde\omega = {}^bR_s$ (`None` without
    a sensor pose), all as entries."""
    x, s, j = carry
    omega, acc, d_aw, dt = sample
    x_next, blocks, k = _entry_kinematics(x, omega, acc, d_aw, dt, d_aa)
    s_next = _entry_covariance(s, blocks, noise, dt, k)
    return (x_next, s_next, _entry_bias_jacobian(j, blocks, dt, k)), None


def _entry_kinematics(x, omega, acc, d_aw, dt, d_aa):
    r"""The state after one sample and the blocks of the step's Jacobians, on entries
    (`_entry_step`): `(x_next, (a00, a10, c_w, p_a, p_w), k)` with `a00` $= I + H\delta t$,
    `a10` $= A_{p\theta}$, `c_w` $= C_\theta$, `p_a` $= B_p$, `p_w` the lever arm's
    $\partial p^+/\partial\tilde\omega$ (`None` without a sensor pose) and $k = 2/\delta t$.
    Values are materialized (`_materialize`) after the rotation's coefficients and after the
    blocks."""
    theta, p, v = x[0:3], x[3:6], x[6:9]
    t0, t1, t2 = theta
    s = t0 * t0 + t1 * t1 + t2 * t2
    half_cos, half_sinc, g1, g2, g3 = kernels.so3_exp_coefficients(s)
    d, d_prime = kernels.so3_jr_inverse_coefficients(s, half_cos, half_sinc)
    s, g1, g2, g3, d, d_prime = _materialize((s, g1, g2, g3, d, d_prime))
    delta = ((1.0, 0.0, 0.0), (0.0, 1.0, 0.0), (0.0, 0.0, 1.0))
    w = ((0.0, -t2, t1), (t2, 0.0, -t0), (-t1, t0, 0.0))
    w2 = tuple(tuple(theta[i] * theta[j] - s * delta[i][j] for j in range(3)) for i in range(3))

    def eye_plus(c1, c2):  # I + c1 W + c2 W²
        return tuple(
            tuple(delta[i][j] + c1 * w[i][j] + c2 * w2[i][j] for j in range(3)) for i in range(3)
        )

    rotation, jr, jr_inv = eye_plus(g1, g2), eye_plus(-g2, g3), eye_plus(0.5, d)
    t_dot_w = t0 * omega[0] + t1 * omega[1] + t2 * omega[2]
    u = tuple(theta[i] * t_dot_w - s * omega[i] for i in range(3))  # θ × (θ × ω)
    t_cross_w = (
        t1 * omega[2] - t2 * omega[1],
        t2 * omega[0] - t0 * omega[2],
        t0 * omega[1] - t1 * omega[0],
    )
    w_tangent = tuple(omega[i] + 0.5 * t_cross_w[i] + d * u[i] for i in range(3))
    skew_w = ((0.0, -omega[2], omega[1]), (omega[2], 0.0, -omega[0]), (-omega[1], omega[0], 0.0))
    a00 = tuple(
        tuple(
            delta[i][j]
            + dt
            * (
                -0.5 * skew_w[i][j]
                + d * (t_dot_w * delta[i][j] + theta[i] * omega[j] - 2.0 * omega[i] * theta[j])
                + 2.0 * d_prime * u[i] * theta[j]
            )
            for j in range(3)
        )
        for i in range(3)
    )
    a_nav = tuple(sum(rotation[i][n] * acc[n] for n in range(3)) for i in range(3))
    dt22, k = 0.5 * dt * dt, 2.0 / dt
    x_next = (
        tuple(theta[i] + w_tangent[i] * dt for i in range(3))
        + tuple(p[i] + v[i] * dt + a_nav[i] * dt22 for i in range(3))
        + tuple(v[i] + a_nav[i] * dt for i in range(3))
    )
    # R [-a]x: row i is a × (row i of R).
    r_skew = tuple(
        (
            acc[1] * r[2] - acc[2] * r[1],
            acc[2] * r[0] - acc[0] * r[2],
            acc[0] * r[1] - acc[1] * r[0],
        )
        for r in rotation
    )
    a10 = _scaled(dt22, _mm(r_skew, jr))  # A_vθ = k A_pθ
    c_w, p_a, p_w = _scaled(dt, jr_inv), _scaled(dt22, rotation), None
    if d_aa is not None:
        p_a, p_w, c_w = _mm(p_a, d_aa), _mm(p_a, d_aw), _mm(c_w, d_aa)
    a00, a10, c_w, p_a, p_w = _materialize((a00, a10, c_w, p_a, p_w))
    return x_next, (a00, a10, c_w, p_a, p_w), k


def _entry_covariance(s, blocks, noise, dt, k):
    r"""$\Sigma^+ = A\Sigma A^\top + B\frac{\Sigma_a}{\delta t}B^\top +
    C\frac{\Sigma_g}{\delta t}C^\top + \Sigma_i\delta t$ (position block) on the six upper blocks
    `s` (`_entry_step`), `blocks` of `_entry_kinematics`; values are materialized after
    $A\Sigma$ and the noise terms."""
    tt, tp, tv, pp, pv, vv = s
    a00, a10, c_w, p_a, p_w = blocks
    sigma_a, sigma_g, sigma_i = noise
    cs = _scaled(1.0 / dt, _mm(c_w, sigma_g))
    q_tt = _mmt(cs, c_w, upper=True)
    q_pp = _mmt(_scaled(1.0 / dt, _mm(p_a, sigma_a)), p_a, upper=True)
    if p_w is not None:
        ps = _scaled(1.0 / dt, _mm(p_w, sigma_g))
        q_pp = _sum(q_pp, _mmt(ps, p_w, upper=True))
    tt, pp, vv = _full(tt), _full(pp), _full(vv)
    x_t = (_mm(a00, tt), _mm(a00, tp), _mm(a00, tv))
    m = (_mm(a10, tt), _mm(a10, tp), _mm(a10, tv))
    x_p = (
        _sum(m[0], _t(tp), _scaled(dt, _t(tv))),
        _sum(m[1], pp, _scaled(dt, _t(pv))),
        _sum(m[2], pv, _scaled(dt, vv)),
    )
    x_v = (_sum(_scaled(k, m[0]), _t(tv)), _sum(_scaled(k, m[2]), vv))  # θ and v columns
    x_t, x_p, x_v, q_tt, q_pp = _materialize((x_t, x_p, x_v, q_tt, q_pp))
    xt_a10 = _mmt(x_t[0], a10)
    xp_a10 = _mmt(x_p[0], a10)
    tp_next = _sum(xt_a10, x_t[1], _scaled(dt, x_t[2]))
    tv_next = _sum(_scaled(k, xt_a10), x_t[2])
    pv_next = _sum(_scaled(k, xp_a10), x_p[2], _scaled(k, _full(q_pp)))
    if p_w is not None:
        q_tp = _mmt(cs, p_w)
        tp_next, tv_next = _sum(tp_next, q_tp), _sum(tv_next, _scaled(k, q_tp))
    return (
        _sum(_mmt(x_t[0], a00, upper=True), q_tt),
        tp_next,
        tv_next,
        _sum(
            _upper(xp_a10),
            _upper(x_p[1]),
            _scaled(dt, _upper(x_p[2])),
            q_pp,
            _scaled(dt, _upper(sigma_i)),
        ),
        pv_next,
        _sum(_scaled(k, _mmt(x_v[0], a10, upper=True)), _upper(x_v[1]), _scaled(k * k, q_pp)),
    )


def _entry_bias_jacobian(j, blocks, dt, k):
    r"""$J_b^+ = A J_b - [B, C]$ on the blocks `j` `(θ/b_g, (p/b_a, p/b_g), (v/b_a, v/b_g))`
    (`_entry_step`), `blocks` of `_entry_kinematics`."""
    j_t, j_p, j_v = j
    a00, a10, c_w, p_a, p_w = blocks
    a10_jt = _mm(a10, j_t)
    j_next = (
        _sum(_mm(a00, j_t), _scaled(-1.0, c_w)),
        (
            _sum(j_p[0], _scaled(dt, j_v[0]), _scaled(-1.0, p_a)),
            _sum(a10_jt, j_p[1], _scaled(dt, j_v[1])),
        ),
        (_sum(j_v[0], _scaled(-k, p_a)), _sum(_scaled(k, a10_jt), j_v[1])),
    )
    if p_w is not None:
        j_next = (
            j_next[0],
            (j_next[1][0], _sum(j_next[1][1], _scaled(-1.0, p_w))),
            (j_next[2][0], _sum(j_next[2][1], _scaled(-k, p_w))),
        )
    return j_next


def _entry_scan(gyro, accel, dt, bias, params, keep):
    """`_entry_step` over the samples of one interval (those `keep` holds, `_masked`):
    `(x, covariance, jacobian_bias)`."""
    dtype = gyro.dtype
    acc, omega, d = jax.vmap(_corrected, in_axes=(0, 0, None, None))(accel, gyro, bias, params)
    d_aa, d_aw = (None, None) if d is None else (_entries(d[0][0]), _entries(d[1]))
    noise = tuple(
        _entries(c)
        for c in (
            params.accelerometer_covariance,
            params.gyroscope_covariance,
            params.integration_covariance,
        )
    )
    zero = jnp.zeros((), dtype)
    zero33 = ((zero,) * 3,) * 3
    init = ((zero,) * 9, ((zero,) * 6, zero33, zero33, (zero,) * 6, zero33, (zero,) * 6),
            (zero33, (zero33, zero33), (zero33, zero33)))  # fmt: skip
    x, s, j = _scanned(
        lambda carry, sample: _entry_step(carry, sample, noise, d_aa),
        init,
        keep,
        tuple(omega.T),
        tuple(acc.T),
        d_aw,
        dt,
    )
    cov = _covariance([_stacked(_full(b) if len(b) == 6 else b) for b in s])
    j_t, j_p, j_v = j
    jac = jnp.block(
        [
            [jnp.zeros((3, 3), dtype), _stacked(j_t)],
            [_stacked(j_p[0]), _stacked(j_p[1])],
            [_stacked(j_v[0]), _stacked(j_v[1])],
        ]
    )
    return jnp.stack(x), cov, jac
