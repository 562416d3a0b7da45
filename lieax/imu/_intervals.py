r"""A stream's intervals of different lengths preintegrated in one compiled call: each interval's
samples padded, on the host, to a bucketed length with a per-sample mask (`preintegrate`'s
`mask`), the number of intervals padded to a bucket too, so that streams whose lengths vary
compile one program per pair of buckets, not one per length.
"""

import jax
import numpy as np

from ._preintegration import (
    BiasRandomWalk,
    ImuError,
    ImuParams,
    preintegrate,
    preintegrate_combined,
)


def bucket_size(n: int) -> int:
    r"""The padded length of `n` samples (or intervals): the smallest multiple of
    $2^{\max(b - 2, 0)}$ at or above `n`, $b$ the bit length of $n - 1$ ($2^{b-1} < n \le 2^b$):
    buckets 3 and 4 times $2^{b-2}$, two per doubling, at most a third of the padded rows masked
    (the rule of `lieax.icp`'s cloud buckets with half as many buckets: IMU samples are cheap to
    pad, compilations are not). Sizes up to 4 are their own bucket. E.g. 7, 8 → 8; 9…12 → 12;
    13…16 → 16; 17…24 → 24; 190…200 → 192, 256."""
    step = 1 << max((n - 1).bit_length() - 2, 0)
    return -(-n // step) * step


@jax.jit
def _batched(params, bias, accel, gyro, dt, mask):
    def one(b, a, g, d, m):
        return preintegrate(params, b, accel=a, gyro=g, dt=d, mask=m)

    return jax.vmap(one)(bias, accel, gyro, dt, mask)


@jax.jit
def _batched_combined(params, walk, bias, accel, gyro, dt, mask):
    def one(b, a, g, d, m):
        return preintegrate_combined(params, walk, b, accel=a, gyro=g, dt=d, mask=m)

    return jax.vmap(one)(bias, accel, gyro, dt, mask)


def _interval_samples(accel, gyro, dt):
    """Per interval `(accel, gyro, dt)` NumPy arrays, checked: `ImuError` naming the interval and
    the sample."""
    if isinstance(accel, np.ndarray | jax.Array) and np.ndim(accel) != 3:
        raise ImuError(
            f"accel must be a sequence of (N_k, 3) arrays or an (m, N, 3) array, got shape "
            f"{np.shape(accel)}."
        )
    accel, gyro = list(accel), list(gyro)
    if len(accel) != len(gyro):
        raise ImuError(f"accel has {len(accel)} intervals, gyro {len(gyro)}.")
    if not accel:
        raise ImuError("no intervals.")
    scalar = isinstance(dt, int | float) or (hasattr(dt, "ndim") and dt.ndim == 0)
    dts = [dt] * len(accel) if scalar else list(dt)
    if len(dts) != len(accel):
        raise ImuError(f"dt has {len(dts)} intervals, accel {len(accel)}.")
    out = []
    for k, (a, g, d) in enumerate(zip(accel, gyro, dts)):
        a, g = np.asarray(a), np.asarray(g)
        for name, x in (("accel", a), ("gyro", g)):
            if x.ndim != 2 or x.shape[1] != 3 or x.shape[0] == 0:
                raise ImuError(f"interval {k}: {name} must be (samples >= 1, 3), got {x.shape}.")
        if a.shape != g.shape:
            raise ImuError(f"interval {k}: accel {a.shape} and gyro {g.shape} differ.")
        d = np.broadcast_to(np.asarray(d), a.shape[:1]) if np.ndim(d) == 0 else np.asarray(d)
        if d.shape != a.shape[:1]:
            raise ImuError(f"interval {k}: dt must be a scalar or ({a.shape[0]},), got {d.shape}.")
        bad = ~(np.isfinite(a).all(1) & np.isfinite(g).all(1) & np.isfinite(d) & (d > 0))
        if bad.any():
            j = int(np.flatnonzero(bad)[0])
            raise ImuError(
                f"interval {k}, sample {j}: non-finite accel, gyro or dt, or dt <= 0 "
                f"(dt = {float(d[j])})."
            )
        out.append((a, g, d))
    return out


def preintegrate_intervals(
    params: ImuParams,
    bias=None,
    *,
    accel,
    gyro,
    dt,
    walk: BiasRandomWalk | None = None,
    buckets=True,
):
    r"""Preintegrate the intervals of a stream, of any numbers of samples, in one compiled call:
    `vmap(preintegrate)` over the intervals padded to one length with a mask (`preintegrate`'s
    `mask`; the padded samples are skipped, the results equal each interval's own to rounding,
    bit for bit on the CPU measured). The padding and the checks are NumPy on the host; with
    `buckets`, the padded length is `bucket_size` of the longest interval and the number of
    intervals is padded to `bucket_size` of it (with empty intervals, cut from the result), so a
    stream of intervals of 7…13 samples compiles at most two programs (buckets 8 and 16) however
    the counts vary, and a growing window one per bucket of its length. As GTSAM's
    `PreintegratedImuMeasurements(params, bias)` per interval and an
    `integrateMeasurement(accel[k][n], gyro[k][n], dt[k][n])` loop.

    **Arguments:**
    - `params`: an `ImuParams`; `bias`: `None` (zero), `(6,)` for every interval or `(m, 6)`.
    - `accel`, `gyro` (keyword-only): one `(N_k, 3)` array per interval (a list, or an
      `(m, N, 3)` array), m/s² and rad/s in the sensor frame.
    - `dt` (keyword-only): a scalar for every sample, or per interval a scalar or `(N_k,)`.
    - `walk`: a `BiasRandomWalk` to preintegrate as `preintegrate_combined` (GTSAM's
      `PreintegratedCombinedMeasurements`), or `None`.
    - `buckets`: pad to buckets (default) or to exactly the longest interval and `m`.

    **Returns:** a `Preintegrated` batched `(m,)` (`imu_factor`'s input), or with `walk`
    `(pim, covariance)`, `covariance` `(m, 15, 15)` (`combined_imu_factor`'s). Raises `ImuError`
    naming the interval and sample of a bad value (non-finite, `dt <= 0`) or shape.
    """
    if not isinstance(params, ImuParams):
        raise TypeError(f"params must be an ImuParams, got {type(params).__name__}.")
    intervals = _interval_samples(accel, gyro, dt)
    m = len(intervals)
    longest = max(len(d) for _, _, d in intervals)
    rows = bucket_size(longest) if buckets else longest
    count = bucket_size(m) if buckets else m
    dtype = np.result_type(*(x for interval in intervals for x in interval))
    dtype = dtype if np.issubdtype(dtype, np.floating) else np.dtype(np.float64)
    padded_accel = np.zeros((count, rows, 3), dtype)
    padded_gyro = np.zeros((count, rows, 3), dtype)
    padded_dt = np.zeros((count, rows), dtype)
    mask = np.zeros((count, rows), bool)
    mask[m:, 0] = True  # the empty intervals: one zero sample held 1 s (cut from the result)
    padded_dt[m:, 0] = 1.0
    for k, (a, g, d) in enumerate(intervals):
        n = len(d)
        padded_accel[k, :n], padded_gyro[k, :n], padded_dt[k, :n] = a, g, d
        mask[k, :n] = True
    bias = np.zeros(6, dtype) if bias is None else np.asarray(bias, dtype)
    if bias.shape not in ((6,), (m, 6)):
        raise ImuError(f"bias must be (6,) or (m, 6) = ({m}, 6), got {bias.shape}.")
    biases = np.zeros((count, 6), dtype)
    biases[:m] = bias
    arrays = (biases, padded_accel, padded_gyro, padded_dt, mask)
    if walk is None:
        result = _batched(params, *arrays)
    else:
        result = _batched_combined(params, walk, *arrays)
    if count == m:
        return result
    return jax.tree.map(lambda x: jax.device_put(np.asarray(x)[:m]), result)
