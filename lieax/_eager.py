"""Array functions that run as one compiled program when called outside `jit`.

JAX runs a function called eagerly (in a notebook, on concrete arrays, or under an eager `grad`,
`jvp` or `vmap`) one operation at a time, and compiles a small XLA program for each operation on
first use: an eager `SE3 @ points` compiled 13 programs, `T.rplus(d).rminus(T)` 27 (issue 30).
`compiled_when_eager(kernel)` calls `jax.jit(kernel)` instead, one program per (kernel, shapes),
served by JAX's persistent cache in a later process; while a `jit` (or `scan`, `while_loop`, ...)
is staging a program, it calls `kernel` itself, so that the caller's program is exactly what it
was, with no nested call in it.

Whether a program is being staged is read from JAX's trace context (`jax._src.core.trace_ctx`,
the chain of `parent_trace`s); a JAX without it counts as staging, i.e. the kernel runs as
written: that only costs compilations, never changes a value.
"""

import functools

import jax

try:
    from jax._src.core import trace_ctx as _trace_ctx
    from jax._src.interpreters.partial_eval import DynamicJaxprTrace as _StagingTrace
except ImportError:  # pragma: no cover (a JAX that moved them: run kernels as written)
    _trace_ctx = _StagingTrace = None


def staging() -> bool:
    """Whether a program is being staged out (`jit`, `scan`, ...) around the current call."""
    if _trace_ctx is None:
        return True
    trace = getattr(_trace_ctx, "trace", None)
    while trace is not None:
        if isinstance(trace, _StagingTrace):
            return True
        trace = getattr(trace, "parent_trace", None)
    return False


def compiled_when_eager(kernel):
    """`kernel` (a function of arrays, positional arguments only), compiled as one program when
    called outside a staged program, as itself inside one (see the module docstring)."""
    compiled = jax.jit(kernel)

    @functools.wraps(kernel)
    def call(*arrays):
        return kernel(*arrays) if staging() else compiled(*arrays)

    return call
