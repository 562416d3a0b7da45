"""The native library (`lieax._native`, built from `csrc/` by `pip install`): it loads, its probe
handler runs inside `jit`, and a program that calls it is served by JAX's persistent compilation
cache in a second process (the reason it exists: JAX never caches a program with a Python host
callback)."""

import textwrap

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from _child import child_output

from lieax import _native

pytestmark = pytest.mark.skipif(
    not _native.available(), reason="the native library is not built (see setup.py)"
)


def test_probe_runs_inside_jit():
    x = jnp.arange(5.0, dtype=jnp.float64) if jax.config.jax_enable_x64 else None
    if x is None:
        pytest.skip("the probe handler takes float64")
    call = jax.ffi.ffi_call("lieax_probe", jax.ShapeDtypeStruct(x.shape, x.dtype))
    np.testing.assert_array_equal(jax.jit(call)(x), 2.0 * np.arange(5.0))


CHILD = textwrap.dedent(
    """
    import sys, jax
    jax.config.update("jax_enable_x64", True)
    import jax.numpy as jnp, lieax
    from lieax import _native
    lieax.enable_compilation_cache(sys.argv[1])
    events = []
    jax.monitoring.register_event_listener(lambda event, **kw: events.append(event))
    assert _native.available()

    @jax.jit
    def f(x):
        return jnp.sin(jax.ffi.ffi_call("lieax_probe", jax.ShapeDtypeStruct(x.shape, x.dtype))(x))

    f(jnp.linspace(0.0, 1.0, 7)).block_until_ready()
    print(sum(e == "/jax/compilation_cache/cache_hits" for e in events))
    """
)


def test_program_with_native_call_is_cached(tmp_path):
    run = lambda: child_output(CHILD, tmp_path).split()[-1]
    assert run() == "0"  # first process: compiled and written
    assert int(run()) >= 1  # second process: read back
