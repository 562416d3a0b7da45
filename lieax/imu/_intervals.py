r"""A stream's intervals of different lengths preintegrated in one compiled call: each interval's
samples padded, on the host, to a bucketed length with a per-sample mask (`preintegrate`'s
`mask`), the number of intervals padded to a bucket too, so that streams whose lengths vary
compile one program per pair of buckets, not one per length.
"""

from collections.abc import Sequence
from typing import overload

import jax
import numpy as np
from jax.typing import ArrayLike

from .. import _executable_store as executable_store
from .._bucket_sizes import bucket_size
from ._combined import preintegrate_combined
from ._params import BiasRandomWalk, ImuError, ImuParams
from ._preintegrated import Preintegrated
from ._sequential import preintegrate


@executable_store.jit
def _batched(params, bias, accel, gyro, dt, mask):
    def one(b, a, g, d, m):
        return preintegrate(params, b, accel=a, gyro=g, dt=d, mask=m)

    return jax.vmap(one)(bias, accel, gyro, dt, mask)


@executable_store.jit
def _batched_combined(params, walk, bias, accel, gyro, dt, mask):
    def one(b, a, g, d, m):
        return preintegrate_combined(params, walk, b, accel=a, gyro=g, dt=d, mask=m)

    return jax.vmap(one)(bias, accel, gyro, dt, mask)


def _stream(accel, gyro, dt):
    """The intervals' samples concatenated, `(accel, gyro, dt, lengths)` NumPy, checked in one
    pass: `ImuError` naming the interval and the sample of a bad value or shape."""
    if isinstance(accel, np.ndarray | jax.Array) and np.ndim(accel) != 3:
        raise ImuError(
            f"accel must be a sequence of (N_k, 3) arrays or an (m, N, 3) array, got shape "
            f"{np.shape(accel)}."
        )
    accel, gyro = [np.asarray(a) for a in accel], [np.asarray(g) for g in gyro]
    if len(accel) != len(gyro):
        raise ImuError(f"accel has {len(accel)} intervals, gyro {len(gyro)}.")
    if not accel:
        raise ImuError("no intervals.")
    for k, (a, g) in enumerate(zip(accel, gyro)):
        if a.ndim != 2 or a.shape[1:] != (3,) or a.shape[0] == 0:
            raise ImuError(f"interval {k}: accel must be (samples >= 1, 3), got {a.shape}.")
        if a.shape != g.shape:
            raise ImuError(f"interval {k}: accel {a.shape} and gyro {g.shape} differ.")
    lengths = np.array([len(a) for a in accel])
    if not isinstance(dt, list | tuple) and np.ndim(dt) == 0:
        dt = np.full(lengths.sum(), float(dt))
    else:
        dts = list(dt)
        if len(dts) != len(accel):
            raise ImuError(f"dt has {len(dts)} intervals, accel {len(accel)}.")
        for k, (d, n) in enumerate(zip(dts, lengths)):
            if np.ndim(d) not in (0, 1) or np.ndim(d) == 1 and len(d) != n:
                raise ImuError(f"interval {k}: dt must be a scalar or ({n},), got {np.shape(d)}.")
        dt = np.concatenate(
            [np.broadcast_to(np.asarray(d, float), (n,)) for d, n in zip(dts, lengths)]
        )
    accel, gyro = np.concatenate(accel), np.concatenate(gyro)
    bad = ~(np.isfinite(accel).all(1) & np.isfinite(gyro).all(1) & np.isfinite(dt) & (dt > 0))
    if bad.any():
        first = int(np.flatnonzero(bad)[0])
        k = int(np.searchsorted(np.cumsum(lengths), first, side="right"))
        j = first - int(lengths[:k].sum())
        raise ImuError(
            f"interval {k}, sample {j}: non-finite accel, gyro or dt, or dt <= 0 "
            f"(dt = {float(dt[first])})."
        )
    return accel, gyro, dt, lengths


@overload
def preintegrate_intervals(
    params: ImuParams,
    bias: ArrayLike | None = None,
    *,
    accel: Sequence[ArrayLike] | ArrayLike,
    gyro: Sequence[ArrayLike] | ArrayLike,
    dt: Sequence[ArrayLike] | ArrayLike,
    walk: None = None,
    buckets: bool = True,
) -> Preintegrated: ...


@overload
def preintegrate_intervals(
    params: ImuParams,
    bias: ArrayLike | None = None,
    *,
    accel: Sequence[ArrayLike] | ArrayLike,
    gyro: Sequence[ArrayLike] | ArrayLike,
    dt: Sequence[ArrayLike] | ArrayLike,
    walk: BiasRandomWalk,
    buckets: bool = True,
) -> tuple[Preintegrated, jax.Array]: ...


def preintegrate_intervals(
    params: ImuParams,
    bias: ArrayLike | None = None,
    *,
    accel: Sequence[ArrayLike] | ArrayLike,
    gyro: Sequence[ArrayLike] | ArrayLike,
    dt: Sequence[ArrayLike] | ArrayLike,
    walk: BiasRandomWalk | None = None,
    buckets: bool = True,
) -> Preintegrated | tuple[Preintegrated, jax.Array]:
    r"""Preintegrate the intervals of a stream, of any numbers of samples, in one compiled call:
    `vmap(preintegrate)` over the intervals padded to one length with a mask (`preintegrate`'s
    `mask`; the padded samples are skipped: each interval's result is its unpadded one, to
    1e-12 in the tests, bit for bit for one interval's scan). The padding and the checks are
    NumPy on the host (no compilation); with `buckets`, the padded length is `bucket_size` of the
    longest interval and the number of intervals is padded to `bucket_size` of it (with empty
    intervals, cut from the result), so calls whose longest intervals hold 7…13 samples compile
    at most three programs (buckets 8, 12 and 16) however the counts vary, and a growing window
    one per bucket of its length (measured, `benchmarks/imu.py`: 500 intervals of 8–12 samples,
    one compilation and 1.7 s of CPU for the first call, against five and 7.7 s for one
    `jit(vmap(preintegrate))` per count; warm 4.5 against 3.6 ms). As GTSAM's
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
    accel, gyro, dt, lengths = _stream(accel, gyro, dt)
    m, longest = len(lengths), int(lengths.max())
    rows = bucket_size(longest) if buckets else longest
    count = bucket_size(m) if buckets else m
    dtype = np.result_type(accel, gyro, dt)
    dtype = dtype if np.issubdtype(dtype, np.floating) else np.dtype(np.float64)
    starts = np.cumsum(lengths) - lengths
    # sample n of interval k goes to row k * rows + (n - starts[k])
    flat = np.arange(len(dt)) + np.repeat(np.arange(m) * rows - starts, lengths)
    padded_accel = np.zeros((count * rows, 3), dtype)
    padded_gyro = np.zeros((count * rows, 3), dtype)
    padded_dt = np.zeros(count * rows, dtype)
    mask = np.zeros(count * rows, bool)
    padded_accel[flat], padded_gyro[flat], padded_dt[flat], mask[flat] = accel, gyro, dt, True
    empty = np.arange(m, count) * rows  # the empty intervals: one zero sample held 1 s (cut)
    padded_dt[empty], mask[empty] = 1.0, True
    padded_accel = padded_accel.reshape(count, rows, 3)
    padded_gyro = padded_gyro.reshape(count, rows, 3)
    padded_dt, mask = padded_dt.reshape(count, rows), mask.reshape(count, rows)
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
