r"""Pinhole calibrations: normalized image coordinates $p = (x, y)$ to pixels, with closed-form
Jacobians. A calibration is an array whose last axis is GTSAM's `vector()` of the same model:

- `Cal3_S2`, 5 numbers $(f_x, f_y, s, u_0, v_0)$ (GTSAM's `Cal3_S2::uncalibrate`):
  $$u = f_x x + s y + u_0, \qquad v = f_y y + v_0,$$
  $$\frac{\partial (u, v)}{\partial p} = K_2 = \begin{bmatrix} f_x & s \\ 0 & f_y \end{bmatrix},
  \qquad \frac{\partial (u, v)}{\partial (f_x, f_y, s, u_0, v_0)} =
  \begin{bmatrix} x & 0 & y & 1 & 0 \\ 0 & y & 0 & 0 & 1 \end{bmatrix}.$$
- `Cal3DS2`, 9 numbers $(f_x, f_y, s, u_0, v_0, k_1, k_2, p_1, p_2)$, radial-tangential
  distortion then `Cal3_S2` (GTSAM's `Cal3DS2_Base::uncalibrate`; Brown-Conrady, OpenCV's
  first four coefficients): with $r^2 = x^2 + y^2$ and $g = 1 + k_1 r^2 + k_2 r^4$,
  $$d = g\,p + \begin{bmatrix} 2 p_1 x y + p_2 (r^2 + 2x^2) \\
  p_1 (r^2 + 2y^2) + 2 p_2 x y \end{bmatrix}, \qquad (u, v) = K_2 d + (u_0, v_0),$$
  $$\frac{\partial (u, v)}{\partial p} = K_2 \frac{\partial d}{\partial p}, \quad
  \frac{\partial d}{\partial p} = g I + p\,\nabla g^\top + \begin{bmatrix}
  2p_1 y + 6 p_2 x & 2 p_1 x + 2 p_2 y \\ 2 p_1 x + 2 p_2 y & 6 p_1 y + 2 p_2 x
  \end{bmatrix}, \quad \nabla g = 2(k_1 + 2 k_2 r^2)\,p,$$
  $$\frac{\partial (u, v)}{\partial (f_x, f_y, s, u_0, v_0)} =
  \begin{bmatrix} d_x & 0 & d_y & 1 & 0 \\ 0 & d_y & 0 & 0 & 1 \end{bmatrix}, \qquad
  \frac{\partial (u, v)}{\partial (k_1, k_2, p_1, p_2)} = K_2 \begin{bmatrix}
  x r^2 & x r^4 & 2xy & r^2 + 2x^2 \\ y r^2 & y r^4 & r^2 + 2y^2 & 2xy \end{bmatrix}$$
  (GTSAM's `D2dintrinsic` and `D2dcalibration`).
"""

import jax
import jax.numpy as jnp
from jax.typing import ArrayLike

from .._checks import broadcast_batch, check_last_axis

LAYOUTS = {5: "Cal3_S2: fx, fy, s, u0, v0", 9: "Cal3DS2: fx, fy, s, u0, v0, k1, k2, p1, p2"}


def check_calibration(calibration, what):
    """`calibration` as a float array with 5 (`Cal3_S2`) or 9 (`Cal3DS2`) entries on its last
    axis; `ValueError` naming `what` otherwise."""
    return check_last_axis(calibration, calibration_size(calibration, what), what)


def calibration_size(calibration, what):
    """5 or 9, the last axis of a pinhole calibration; `ValueError` naming `what` otherwise."""
    size = jnp.shape(calibration)[-1] if jnp.ndim(calibration) else None
    if size not in LAYOUTS:
        raise ValueError(
            f"{what} must have shape (*batch, 5) (Cal3_S2: fx, fy, s, u0, v0) or "
            "(*batch, 9) (Cal3DS2: fx, fy, s, u0, v0, k1, k2, p1, p2), got shape "
            f"{tuple(jnp.shape(calibration))}."
        )
    return size


def _distortion(calibration, p):
    """`(d, g)`: the distorted point $d$ and the radial factor $g$ (module docstring)."""
    x, y = p[..., 0], p[..., 1]
    k1, k2, p1, p2 = (calibration[..., k] for k in range(5, 9))
    xx, yy, xy = x * x, y * y, x * y
    rr = xx + yy
    g = 1 + rr * (k1 + k2 * rr)
    d = jnp.stack(
        [g * x + 2 * p1 * xy + p2 * (rr + 2 * xx), g * y + p1 * (rr + 2 * yy) + 2 * p2 * xy], -1
    )
    return d, g


def pixel(calibration, p):
    """The pixel of normalized coordinates `p` (no checks; the value of `uncalibrate`)."""
    d = p if calibration.shape[-1] == 5 else _distortion(calibration, p)[0]
    return jnp.einsum("...ij,...j->...i", _k2(calibration), d) + calibration[..., 3:5]


def _distorted(calibration, p):
    """`(d, dd_dp, dd_dk)`: the distorted point, its `(*, 2, 2)` Jacobian in $p$ and `(*, 2, 4)`
    in $(k_1, k_2, p_1, p_2)$; the identity when the calibration has no distortion."""
    if calibration.shape[-1] == 5:
        eye = jnp.broadcast_to(jnp.eye(2, dtype=p.dtype), p.shape[:-1] + (2, 2))
        return p, eye, None
    x, y = p[..., 0], p[..., 1]
    k1, k2, p1, p2 = (calibration[..., k] for k in range(5, 9))
    xx, yy, xy = x * x, y * y, x * y
    rr = xx + yy
    d, g = _distortion(calibration, p)
    dg = 2 * (k1 + 2 * k2 * rr)
    cross_term = 2 * p1 * x + 2 * p2 * y
    dd_dp = jnp.stack(
        [
            jnp.stack([g + dg * xx + 2 * p1 * y + 6 * p2 * x, dg * xy + cross_term], -1),
            jnp.stack([dg * xy + cross_term, g + dg * yy + 6 * p1 * y + 2 * p2 * x], -1),
        ],
        -2,
    )
    dd_dk = jnp.stack(
        [
            jnp.stack([x * rr, x * rr * rr, 2 * xy, rr + 2 * xx], -1),
            jnp.stack([y * rr, y * rr * rr, rr + 2 * yy, 2 * xy], -1),
        ],
        -2,
    )
    return d, dd_dp, dd_dk


def _k2(calibration):
    fx, fy, s = calibration[..., 0], calibration[..., 1], calibration[..., 2]
    zero = jnp.zeros_like(fx)
    return jnp.stack([jnp.stack([fx, s], -1), jnp.stack([zero, fy], -1)], -2)


def uncalibrate(calibration: ArrayLike, p: ArrayLike) -> jax.Array:
    r"""The pixel $(u, v)$ of normalized image coordinates $p$ `(*batch, 2)` under a `Cal3_S2`
    `(*batch, 5)` or `Cal3DS2` `(*batch, 9)` calibration (module docstring; GTSAM's
    `uncalibrate`). Batch shapes broadcast."""
    calibration = check_calibration(calibration, "uncalibrate: calibration")
    p = check_last_axis(p, 2, "uncalibrate: p", "x, y")
    broadcast_batch("uncalibrate", calibration.shape[:-1], p.shape[:-1])
    return pixel(calibration, p)


def uncalibrate_jacobians(
    calibration: ArrayLike, p: ArrayLike
) -> tuple[jax.Array, jax.Array, jax.Array]:
    r"""`(pixel, J_pixel_calibration, J_pixel_p)`, shapes `(*batch, 2)`, `(*batch, 2, n)`
    (n = 5 or 9, GTSAM's `Dcal`) and `(*batch, 2, 2)` (GTSAM's `Dp`), in closed form (module
    docstring)."""
    calibration = check_calibration(calibration, "uncalibrate_jacobians: calibration")
    p = check_last_axis(p, 2, "uncalibrate_jacobians: p", "x, y")
    batch = broadcast_batch("uncalibrate_jacobians", calibration.shape[:-1], p.shape[:-1])
    calibration = jnp.broadcast_to(calibration, (*batch, calibration.shape[-1]))
    p = jnp.broadcast_to(p, (*batch, 2))
    d, dd_dp, dd_dk = _distorted(calibration, p)
    K2 = _k2(calibration)
    value = jnp.einsum("...ij,...j->...i", K2, d) + calibration[..., 3:5]
    one, zero = jnp.ones_like(d[..., 0]), jnp.zeros_like(d[..., 0])
    J_linear = jnp.stack(
        [
            jnp.stack([d[..., 0], zero, d[..., 1], one, zero], -1),
            jnp.stack([zero, d[..., 1], zero, zero, one], -1),
        ],
        -2,
    )
    J_calibration = J_linear if dd_dk is None else jnp.concatenate([J_linear, K2 @ dd_dk], -1)
    return value, J_calibration, K2 @ dd_dp
