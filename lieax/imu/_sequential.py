r"""`preintegrate`: one interval by a sequential `lax.scan` (GTSAM's `TangentPreintegration`,
exactly), on 3×3 blocks (`_block_scan`) and, under `vmap` over a batch of many samples, entry by
entry (`_entry_scan`), whichever compiles and runs the batch faster (`_dispatch_batched`);
derivatives go through the block scan.
"""

import jax
import jax.numpy as jnp
import numpy as np

from .._checks import is_concrete, to_device
from ._block_scan import _block_scan
from ._entry_scan import _entry_scan
from ._params import ImuParams
from ._preintegrated import Preintegrated, _result
from ._samples import _check_samples, _delta_t, _samples_by_keyword


@jax.custom_batching.custom_vmap
def _dispatch(gyro, accel, dt, bias, params, keep):
    """`_block_scan`, and `_entry_scan` under `vmap` (`_dispatch_batched`)."""
    return _block_scan(gyro, accel, dt, bias, params, keep)


# Batches of fewer samples (intervals × samples per interval) than this run `_block_scan`.
_ENTRYWISE_MIN_SAMPLES = 1 << 23


@_dispatch.def_vmap
def _dispatch_batched(axis_size, in_batched, gyro, accel, dt, bias, params, keep):
    """Over a batch of intervals the 3×3 products of `_tangent_step` run as batched tiny dots,
    which XLA's CPU backend vectorizes poorly; `_entry_scan` writes them out so that every
    operation is elementwise over the intervals (measured, one core: 1.6–1.7× faster than
    `_block_scan` for 1000 intervals of 200 samples; on a single interval it is 4.5× slower).
    Its program is 4× longer (~3000 StableHLO lines against ~700: every 3×3 product written
    out), and XLA compiles it in 3.6–4.0 s of CPU against 1.2–1.4 s, which only batches of many
    samples repay in one call: batches under `_ENTRYWISE_MIN_SAMPLES` samples ($2^{23}$, where
    the warm gain of one call, ~0.3 µs a sample, reaches the extra compile time) run
    `_block_scan`. Measured 2026-12-04 on the 2-core machine under load 6, compile / warm
    median: 512 intervals of 256 samples 1.9 s / 152 ms by 3×3 blocks against 6.0 s / 156 ms
    entrywise; 2048 of 256, 3.3 s / 0.68 s against 11.3 s / 0.51 s (the IMU smoother of 500
    intervals of 200 samples compiled the entrywise scan with the threshold at $2^{17}$, its
    first call 6.7 s, issue 30); 512 of 12, 3.9 ms against 2.7 ms; 64 of 200, 6.2 against
    9.3 ms."""
    in_axes = jax.tree.map(lambda batched: 0 if batched else None, tuple(in_batched))
    small = axis_size * gyro.shape[-2] < _ENTRYWISE_MIN_SAMPLES
    scan = _block_scan if small else _entry_scan
    outputs = jax.vmap(scan, in_axes=in_axes)(gyro, accel, dt, bias, params, keep)
    return outputs, (True, True, True)


@jax.custom_jvp
def _scan(gyro, accel, dt, bias, params, keep):
    """`_dispatch`, differentiated through `_block_scan` (`custom_vmap` has no reverse mode)."""
    return _dispatch(gyro, accel, dt, bias, params, keep)


@_scan.defjvp
def _scan_jvp(primals, tangents):
    return jax.jvp(_block_scan, primals, tangents)


@_samples_by_keyword
def preintegrate(params: ImuParams, bias=None, *, accel, gyro, dt, mask=None) -> Preintegrated:
    r"""Preintegrate the samples of one interval by a sequential `lax.scan`, exactly as GTSAM's
    `PreintegratedImuMeasurements(params, bias).integrateMeasurement(accel[k], gyro[k], dt[k])`
    for $k = 0 \dots N-1$ (see `_tangent_step`). `vmap` it over intervals (e.g.
    `jax.vmap(lambda a, g, d: preintegrate(params, bias, accel=a, gyro=g, dt=d))`, or
    `preintegrate_intervals` for intervals of different lengths): a batch of $2^{23}$ samples or
    more then runs a scan elementwise over the intervals (`_entry_step`; measured,
    `benchmarks/imu.py`: 1000 intervals of 200 samples in float64 on one core, 1.7× faster than
    the batched 3×3 blocks and 7–8× faster than GTSAM's C++ loop called from Python, 5× once
    under heavy contention), a smaller one the batched 3×3 blocks, which compile in a third of
    the time: below $2^{23}$ samples one call's gain does not repay the compilation
    (`_dispatch_batched`).

    **Arguments:**

    - `params`: an `ImuParams`.
    - `bias`: $\hat b = (b_a, b_g)$, `(6,)`, the bias the samples are corrected with
      (`None`: zero; GTSAM's `biasHat`).
    - `accel`, `gyro` (keyword-only): samples in the sensor frame, `(N, 3)` each (m/s², rad/s).
    - `dt` (keyword-only): the time each sample is held, a scalar or `(N,)`; from timestamps
      `t` (`N + 1` of them), `dt = jnp.diff(t)`.
    - `mask`: `None`, or boolean `(N,)`, `True` for the samples to integrate: the others are
      skipped (their values are not read, `dt` may be 0), so that intervals of different lengths
      padded to one `N` batch under `vmap` and give the unpadded results (bit for bit here).

    **Returns:** a `Preintegrated`, in the dtype of the samples, `dt` and `bias` (float32 or
    float64; `params` is cast to it). Raises `ImuError` on bad shapes, and, outside tracing, on
    non-finite samples or `dt <= 0` (naming the sample) or an all-False `mask`; under
    `jit`/`vmap` those give `valid=False` and NaN fields instead. A positional `accel`, `gyro`
    or `dt` is a `TypeError` that names the keywords.
    """
    gyro, accel, dt, bias, keep, ok = _check_samples(gyro, accel, dt, bias, params, mask)
    dtype = jnp.result_type(gyro, accel, dt, bias)
    gyro, accel, dt, bias = (a.astype(dtype) for a in (gyro, accel, dt, bias))
    params = jax.tree.map(
        lambda a: to_device(np.asarray(a, dtype)) if is_concrete(a) else jnp.asarray(a, dtype),
        params,
    )
    x, cov, jac = _scan(gyro, accel, dt, bias, params, keep)
    return _result(x, _delta_t(dt, keep), cov, jac, bias, ok)
