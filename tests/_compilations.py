"""`compilations()`: the names of the XLA programs compiled inside a block, counted with JAX's
monitoring events (one `backend_compile_duration` per XLA program)."""

import contextlib

import jax

_COMPILED = []
jax.monitoring.register_event_duration_secs_listener(
    lambda event, seconds, **kw: (
        _COMPILED.append(kw.get("fun_name"))
        if event == "/jax/core/compile/backend_compile_duration"
        else None
    )
)


@contextlib.contextmanager
def compilations():
    """The names of the XLA programs compiled inside the block (a list, filled when it ends)."""
    start = len(_COMPILED)
    found = []
    yield found
    found.extend(_COMPILED[start:])
