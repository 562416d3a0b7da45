r"""Constructors on concrete inputs, in NumPy: building a problem compiles nothing.

Every eager `jax.numpy` operation on a concrete array compiles its own small XLA program the first
time it meets a shape and dtype (10–100 ms each on a 2-core CPU), so a constructor written with
the kernels (`SE2.identity`, `SE3.from_matrix`, ...) made a user wait 0.7–1 s on its first call
(issue 30). With concrete inputs (NumPy arrays, Python numbers, JAX arrays outside any
transformation) the constructors compute their parameters here, in NumPy, in the dtype the kernels
would give, and hand one array to JAX (`lieax._checks.to_device`, a transfer); traced inputs (under
`jit`, `vmap`, `grad`) take the kernels, whose `custom_jvp` rules carry the derivatives. A concrete
input has no derivative to carry. The formulas are the kernels' (same sources); values agree with
them to rounding (`tests/test_first_call.py`).
"""

import numpy as np

from ._series import exp_coefficients


def identity(parameters_dim, batch_shape, dtype):
    """The identity's parameters: one in the first slot, zeros elsewhere, for every lieax group
    (`(1, 0)`, `(1, 0, 0, 0)`, the quaternion `(1, 0, 0, 0)` then zero translation, velocity or
    log-scale)."""
    params = np.zeros((*batch_shape, parameters_dim), dtype=dtype)
    params[..., 0] = 1
    return params


def join(batch, *parts):
    """Parameters from parts (rotation, then translation, ...) broadcast to `batch`, concatenated
    on the last axis."""
    return np.concatenate([np.broadcast_to(p, (*batch, p.shape[-1])) for p in parts], axis=-1)


def so2_exp(theta):
    r"""$(\cos\theta, \sin\theta)$ of angles `(..., 1)` (Solà App. A)."""
    return np.concatenate([np.cos(theta), np.sin(theta)], axis=-1)


def so2_nearest_rotation(m):
    r"""`lieax.groups._so2.nearest_rotation`'s $(c, s)$: $(m_{00} + m_{11},\ m_{10} - m_{01})$
    normalized, the identity where it is zero (a reflection)."""
    part = np.stack([m[..., 0, 0] + m[..., 1, 1], m[..., 1, 0] - m[..., 0, 1]], axis=-1)
    norm = np.linalg.norm(part, axis=-1, keepdims=True)
    degenerate = norm == 0
    part = np.where(degenerate, np.array([1.0, 0.0], dtype=m.dtype), part)
    return (part / np.where(degenerate, 1.0, norm)).astype(m.dtype)


def so3_exp(omega):
    r"""$\mathrm{Exp}(\omega) = (\cos\tfrac\theta2,\ \tfrac{\sin(\theta/2)}{\theta}\,\omega)$, the
    coefficients of `lieax.groups._series.exp_coefficients` (series below its limit)."""
    s = np.sum(omega * omega, axis=-1, keepdims=True)
    half_cos, half_sinc, *_ = exp_coefficients(s, np)
    return np.concatenate([half_cos, half_sinc * omega], axis=-1).astype(omega.dtype)


def se2_exp(xi):
    r"""`lieax.groups._se2`'s $\mathrm{Exp}(v, \omega) = (\cos\omega, \sin\omega, V v)$,
    $V = g_1 I + \omega g_2 J$ (Solà App. C), with $\cos\omega = 2\cos^2\tfrac\omega2 - 1$."""
    v, w = xi[..., :2], xi[..., 2:]
    half_cos, _, g1, g2, _ = exp_coefficients(w * w, np)
    perp_v = np.stack([-v[..., 1], v[..., 0]], axis=-1)
    params = [2 * half_cos * half_cos - 1, w * g1, g1 * v + w * g2 * perp_v]
    return np.concatenate(params, axis=-1).astype(xi.dtype)


def se3_exp(xi):
    r"""`lieax.groups._se3`'s $\mathrm{Exp}(v, \omega) = (\mathrm{Exp}(\omega),\ v + g_2\,
    \omega \times v + g_3\, \omega \times (\omega \times v))$ (Solà App. D)."""
    v, omega = xi[..., :3], xi[..., 3:]
    s = np.sum(omega * omega, axis=-1, keepdims=True)
    half_cos, half_sinc, _, g2, g3 = exp_coefficients(s, np)
    wv = np.cross(omega, v)
    t = v + g2 * wv + g3 * np.cross(omega, wv)
    return np.concatenate([half_cos, half_sinc * omega, t], axis=-1).astype(xi.dtype)


def quaternion_product(p, q):
    r"""$p \otimes q$ (Hamilton, wxyz)."""
    pw, pv, qw, qv = p[..., :1], p[..., 1:], q[..., :1], q[..., 1:]
    w = pw * qw - np.sum(pv * qv, axis=-1, keepdims=True)
    return np.concatenate([w, pw * qv + qw * pv + np.cross(pv, qv)], axis=-1)


def so3_as_matrix(q):
    r"""The rotation matrix of unit quaternions `q` `(..., 4)` (wxyz), $R = I + 2w[v]_\times +
    2[v]_\times^2$ (Solà, "Quaternion kinematics for the error-state Kalman filter", eq. 115)."""
    w, v = q[..., :1, None], q[..., 1:]
    zero = np.zeros_like(v[..., 0])
    skew = np.stack(
        [
            np.stack([zero, -v[..., 2], v[..., 1]], -1),
            np.stack([v[..., 2], zero, -v[..., 0]], -1),
            np.stack([-v[..., 1], v[..., 0], zero], -1),
        ],
        -2,
    )
    return np.eye(3, dtype=q.dtype) + 2 * w * skew + 2 * skew @ skew


def so3_from_matrix(m):
    r"""`lieax.groups._so3._from_matrix`: Shepperd's method, the quaternion from the largest of
    $1 + \mathrm{tr} R$ and $1 + 2R_{ii} - \mathrm{tr} R$, normalized (a rotation for any input)."""
    m00, m11, m22 = m[..., 0, 0], m[..., 1, 1], m[..., 2, 2]
    d21, d02, d10 = (
        m[..., 2, 1] - m[..., 1, 2],
        m[..., 0, 2] - m[..., 2, 0],
        m[..., 1, 0] - m[..., 0, 1],
    )
    s10, s02, s21 = (
        m[..., 1, 0] + m[..., 0, 1],
        m[..., 0, 2] + m[..., 2, 0],
        m[..., 2, 1] + m[..., 1, 2],
    )
    pivots = [1 + m00 + m11 + m22, 1 + m00 - m11 - m22, 1 - m00 + m11 - m22, 1 - m00 - m11 + m22]
    candidates = np.stack(
        [
            np.stack([pivots[0], d21, d02, d10], axis=-1),
            np.stack([d21, pivots[1], s10, s02], axis=-1),
            np.stack([d02, s10, pivots[2], s21], axis=-1),
            np.stack([d10, s02, s21, pivots[3]], axis=-1),
        ],
        axis=-2,
    )
    best = np.argmax(np.stack(pivots, axis=-1), axis=-1)
    q = np.take_along_axis(candidates, best[..., None, None], axis=-2)[..., 0, :]
    return (q / np.linalg.norm(q, axis=-1, keepdims=True)).astype(m.dtype)
