"""`raise_if`: an error raised at run time from inside `jit`, and a status under `vmap`.

The solvers' `throw=True` raises when a solve ends in a failure status. Outside transformations
the status is a concrete number and the solver raises directly. Inside `jit` the status is only
known when the compiled program runs, so `raise_if` passes it through a host callback
(`jax.experimental.io_callback`) that raises there: JAX then stops the program with a
`JaxRuntimeError` whose message carries the solver's error (optimistix's `error_if` works the same
way). Under `vmap` a batch reports per-problem statuses instead (one bad problem must not stop
the others): the callback's batching rule (`jax.custom_batching.custom_vmap`) drops the check.
The check has no derivative to carry (the status is an integer), so `jvp`, `grad` and the
implicit derivatives pass through it.

The persistent compilation cache (`lieax.enable_compilation_cache`): JAX writes no program that
holds a Python callback to it. Called outside `jit`, the solvers (`lstsq.least_squares`,
`FactorGraph.solve`, the ICP registrations) run their compiled loop, which returns the status,
and raise in Python afterwards: `raise_if` is never staged and the loop is cached. Only a solve
with `throw=True` inside the caller's own `jit` stages this callback, so that program (the
caller's) is compiled again in every process: the documented limit; `throw=False` under `jit`
(reading the status) keeps it cacheable.
"""

import jax
import numpy as np
from jax.experimental import io_callback


def raise_if(status, failed, message):
    """`status`, after raising `message(code)` at run time when `failed(code)` holds.

    **Arguments:**

    - `status`: a scalar integer array (concrete or traced).
    - `failed`: `code -> bool` on the host, for the integer status code.
    - `message`: `code -> Exception` on the host: the error to raise.

    **Returns:** `status` unchanged. Under `vmap` no check is made (read the statuses).
    """

    @jax.custom_batching.custom_vmap
    def check(code):
        def host(value):
            value = int(np.asarray(value))
            if failed(value):
                raise message(value)
            return np.asarray(value, dtype=code.dtype)

        shape = jax.ShapeDtypeStruct(code.shape, code.dtype)
        return io_callback(host, shape, code, ordered=False)

    @check.def_vmap
    def _batched(axis_size, in_batched, code):
        return code, in_batched[0]

    return check(status)
