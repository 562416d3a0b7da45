"""Timing helpers shared by the benchmarks: compile, warm up, then time variants interleaved.

Every variant is a zero-argument callable that runs one jitted computation and returns its outputs.
`time_interleaved` compiles and warms each up, picks for each a number of calls per sample so that a
sample lasts at least `min_sample_s` (timer resolution and dispatch jitter matter at tens of
microseconds), then runs `rounds` rounds, in each of which every variant takes one sample, in an
order rotated from round to round. Machine noise (frequency changes, other processes) therefore
falls on all variants alike, and the median per call over rounds is compared. A variant so slow that
its samples would take more than `max_variant_s` in all samples only every k-th round (at least
three samples).
"""

import dataclasses
import math
import statistics
import time

import jax
from _results import markdown_table  # noqa: F401  (the benchmarks import it from here)


@dataclasses.dataclass(frozen=True)
class Timing:
    """Seconds per call over the samples: the `median`, the `best`, and the quartiles."""

    median: float
    best: float
    low: float
    high: float
    samples: int
    calls_per_sample: int
    compile_s: float


def _run(fn):
    return jax.block_until_ready(fn())


def _sample(fn, calls):
    start = time.perf_counter()
    for _ in range(calls):
        _run(fn)
    return (time.perf_counter() - start) / calls


def time_interleaved(variants, rounds, *, warmup=3, min_sample_s=2e-3, max_variant_s=20.0):
    """Seconds per call of each callable in `variants` (a dict name -> callable).

    **Arguments:**
    - `variants`: name -> zero-argument callable returning JAX arrays (each call is waited for).
    - `rounds`: interleaved rounds; each variant takes one sample per round.
    - `warmup`: calls after the compiling call, before calibration.
    - `min_sample_s`: a sample repeats the call until it lasts at least this long.
    - `max_variant_s`: a variant whose `rounds` samples would take longer samples only every k-th
      round, k chosen to stay within this time (but at least 3 samples, or `rounds` if fewer).

    **Returns:** a dict name -> `Timing`, in the order of `variants`.
    """
    if rounds < 1:
        raise ValueError(f"rounds must be at least 1, got {rounds}.")
    names = list(variants)
    compile_s, calls, stride = {}, {}, {}
    for name in names:
        start = time.perf_counter()
        _run(variants[name])
        compile_s[name] = time.perf_counter() - start
        for _ in range(warmup):
            _run(variants[name])
        single = _sample(variants[name], 1)
        calls[name] = max(1, min(1000, math.ceil(min_sample_s / max(single, 1e-9))))
        affordable = max(min(3, rounds), int(max_variant_s / (calls[name] * single)))
        stride[name] = max(1, math.ceil(rounds / affordable))
    samples = {name: [] for name in names}
    for r in range(rounds):
        shift = r % len(names)
        for name in names[shift:] + names[:shift]:
            if r % stride[name] == 0:
                samples[name].append(_sample(variants[name], calls[name]))
    timings = {}
    for name in names:
        values = sorted(samples[name])
        low, high = _quartiles(values)
        timings[name] = Timing(
            median=statistics.median(values),
            best=values[0],
            low=low,
            high=high,
            samples=len(values),
            calls_per_sample=calls[name],
            compile_s=compile_s[name],
        )
    return timings


def _quartiles(values):
    if len(values) < 2:
        return values[0], values[0]
    q = statistics.quantiles(values, n=4, method="inclusive")
    return q[0], q[2]


def format_seconds(seconds):
    """A duration with a unit that keeps three significant digits (µs, ms or s)."""
    for unit, scale in (("s", 1.0), ("ms", 1e-3)):
        if seconds >= scale:
            return f"{seconds / scale:.3g} {unit}"
    return f"{seconds / 1e-6:.3g} µs"


def format_ratio(numerator, denominator):
    return f"{numerator / denominator:.2f}×"


def machine_description():
    """One line naming the JAX version, backend and device, for the benchmark's header."""
    device = jax.devices()[0]
    return (
        f"JAX {jax.__version__}, backend {jax.default_backend()}, device {device.device_kind}, "
        f"x64 {'on' if jax.config.jax_enable_x64 else 'off'}"
    )
