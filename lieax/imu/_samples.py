r"""The samples of one interval, before any preintegration scheme reads them: their checks
(shapes at trace time, values outside tracing; masks), the keyword-only call that keeps a swapped
accelerometer and gyroscope from integrating silently, the bias and sensor-pose correction
(GTSAM's `correctMeasurementsBySensorPose`), a masked `lax.scan` over them and $\Delta t_{ij}$.
"""

import functools
import inspect

import jax
import jax.numpy as jnp
import numpy as np

from .._checks import as_float_array, is_concrete, to_device
from .._linalg import cross
from ._params import ImuError, _check_params


def _check_samples(gyro, accel, dt, bias, params, mask=None):
    """Shapes at trace time; returns `(gyro, accel, dt, bias, keep, ok)`: the arrays (`bias`
    zeros for `None`), `keep` the boolean `mask` (`None` without one) and a `valid` flag
    (raises outside tracing). Masked-out samples do not count: their values are replaced by
    `(0, 0, dt = 1)` so that the step computed for them, and its derivatives, are finite before
    the scan discards it."""
    _check_params(params)
    gyro = as_float_array(gyro, "gyro")
    accel = as_float_array(accel, "accel")
    for name, x in (("gyro", gyro), ("accel", accel)):
        if x.ndim != 2 or x.shape[-1] != 3:
            raise ImuError(f"{name} must have shape (samples, 3), got {x.shape}.")
    if gyro.shape != accel.shape:
        raise ImuError(f"gyro and accel have mismatched shapes {gyro.shape} and {accel.shape}.")
    if gyro.shape[0] == 0:
        raise ImuError("an interval needs at least one sample.")
    dt = as_float_array(dt, "dt")
    if dt.ndim == 0:
        dt = (
            jnp.broadcast_to(dt, gyro.shape[:1])
            if not is_concrete(dt)
            else to_device(np.broadcast_to(np.asarray(dt), gyro.shape[:1]))
        )
    if dt.shape != gyro.shape[:1]:
        raise ImuError(f"dt must be a scalar or have shape ({gyro.shape[0]},), got {dt.shape}.")
    bias = jnp.zeros(6, gyro.dtype) if bias is None else as_float_array(bias, "bias")
    if bias.shape != (6,):
        raise ImuError(f"bias must be (b_acc, b_gyro) of shape (6,), got {bias.shape}.")
    if mask is not None:
        mask = to_device(np.asarray(mask)) if is_concrete(mask) else jnp.asarray(mask)
        if mask.dtype != jnp.bool_ or mask.shape != gyro.shape[:1]:
            raise ImuError(
                f"mask must be boolean of shape ({gyro.shape[0]},) (True for the samples to "
                f"integrate), got {mask.dtype} {mask.shape}."
            )
    if not is_concrete(gyro, accel, dt, mask):
        finite = jnp.isfinite(gyro).all(-1) & jnp.isfinite(accel).all(-1) & jnp.isfinite(dt)
        ok = finite & (dt > 0)
        if mask is not None:
            ok = ok | ~mask
        ok = ok.all() & jnp.isfinite(bias).all()
        if mask is not None:
            ok = ok & mask.any()
            gyro = jnp.where(mask[:, None], gyro, 0.0)
            accel = jnp.where(mask[:, None], accel, 0.0)
            dt = jnp.where(mask, dt, 1.0)
        return gyro, accel, dt, bias, mask, ok
    # concrete samples: checked (and masked) in NumPy, which compiles nothing
    gyro_np, accel_np, dt_np = np.asarray(gyro), np.asarray(accel), np.asarray(dt)
    finite = np.isfinite(gyro_np).all(-1) & np.isfinite(accel_np).all(-1) & np.isfinite(dt_np)
    ok = finite & (dt_np > 0)
    if mask is not None:
        mask_np = np.asarray(mask)
        ok = ok | ~mask_np
    if not ok.all():
        k = int(np.flatnonzero(~ok)[0])
        what = "non-finite gyro, accel or dt" if not finite[k] else "dt <= 0"
        raise ImuError(f"sample {k}: {what} (dt = {float(dt_np[k])}).")
    if mask is not None:
        if not mask_np.any():
            raise ImuError("an interval needs at least one sample (mask is all False).")
        gyro = to_device(np.where(mask_np[:, None], gyro_np, 0.0))
        accel = to_device(np.where(mask_np[:, None], accel_np, 0.0))
        dt = to_device(np.where(mask_np, dt_np, 1.0))
    if is_concrete(bias):
        if not np.isfinite(np.asarray(bias)).all():
            raise ImuError("bias has non-finite values.")
        return gyro, accel, dt, bias, mask, to_device(np.bool_(True))
    return gyro, accel, dt, bias, mask, jnp.isfinite(bias).all()  # a traced bias: its status


def _masked(step):
    r"""`step(carry, sample)` of a scan, made a no-op where the sample's last entry `keep` is
    False (the carry passes through unchanged, bit for bit: a padded interval integrates as the
    unpadded one), or `step` itself when the samples carry no mask (`keep` `None`)."""

    def masked_step(carry, sample):
        *sample, keep = sample
        next_carry, _ = step(carry, tuple(sample))
        return jax.tree.map(lambda new, old: jnp.where(keep, new, old), next_carry, carry), None

    return masked_step


def _scanned(step, init, keep, *arrays):
    """`lax.scan(step, init, arrays)`'s final carry, `_masked` when `keep` is not `None`."""
    if keep is None:
        return jax.lax.scan(step, init, arrays)[0]
    return jax.lax.scan(_masked(step), init, (*arrays, keep))[0]


def _corrected(accel, gyro, bias, params):
    r"""Bias- and sensor-pose-corrected body-frame $(a, \omega)$ and the blocks
    $(\partial a/\partial\tilde a, \partial a/\partial\tilde\omega, \partial\omega/\partial\tilde\omega)$
    (`None` without a sensor pose), GTSAM's
    `correctMeasurementsBySensorPose`: $\omega = {}^bR_s \omega_s$,
    $a = {}^bR_s a_s - \omega \times (\omega \times r)$ with $r$ the lever arm."""
    acc, omega = accel - bias[:3], gyro - bias[3:]
    if params.body_P_sensor is None:
        return acc, omega, None
    b_R_s = params.body_P_sensor.rotation().as_matrix()
    arm = params.body_P_sensor.translation()
    omega_b = b_R_s @ omega
    acc_b = b_R_s @ acc - cross(omega_b, cross(omega_b, arm))
    # d(-ω×(ω×r))/dω = 2 r ωᵀ - (ω·r) I - ω rᵀ, then times bRs (GTSAM's D_correctedAcc_omega).
    d_acc_omega = (
        2.0 * jnp.outer(arm, omega_b)
        - jnp.dot(omega_b, arm) * jnp.eye(3, dtype=acc.dtype)
        - jnp.outer(omega_b, arm)
    ) @ b_R_s
    return acc_b, omega_b, (b_R_s, d_acc_omega, b_R_s)


def _samples_by_keyword(function):
    r"""`function` with a clear `TypeError` when its call does not bind: the samples are
    keyword-only (`accel=`, `gyro=`, `dt=`), since a swapped positional accelerometer and
    gyroscope would integrate silently to a wrong, valid-looking result."""
    signature = inspect.signature(function)
    name = function.__name__

    @functools.wraps(function)
    def checked(*args, **kwargs):
        try:
            signature.bind(*args, **kwargs)
        except TypeError as error:
            raise TypeError(
                f"{name}{signature}: the samples are keyword-only, accel= (m/s²), gyro= (rad/s) "
                f"and dt= (s), as GTSAM's integrateMeasurement(measuredAcc, measuredOmega, dt); "
                f"e.g. {name}(params, bias, accel=accel, gyro=gyro, dt=dt) ({error})."
            ) from None
        return function(*args, **kwargs)

    return checked


def _delta_t(dt, keep):
    r"""$\Delta t_{ij}$: the sum of the kept samples' `dt`."""
    return dt.sum() if keep is None else jnp.where(keep, dt, 0.0).sum()
