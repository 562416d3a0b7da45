"""`lieax._executable_store`: what names a program across processes, and a second process that
loads a factor graph's loop and ICP's instead of tracing and compiling them (issue 30)."""

import textwrap

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from _child import child_output

from lieax import SE2, _executable_store
from lieax._describe import Undescribable, describe, jaxpr_fingerprint, stable_repr
from lieax.factorgraph import Factor, FactorGraph, Var
from lieax.factorgraph._fingerprint import loop_fingerprint
from lieax.lstsq import Huber


def _jaxpr(fun, *args):
    return jaxpr_fingerprint(jax.make_jaxpr(fun)(*args))


def test_describe_names_plain_values_arrays_and_lieax_code():
    assert describe((1, 2.5, "a", None)) == describe((1, 2.5, "a", None))
    assert describe((1, 2)) != describe([1, 2]) != describe((1.0, 2))
    assert describe({"b": 1, "a": 2}) == describe({"a": 2, "b": 1})
    a = np.arange(6.0).reshape(2, 3)
    assert describe(a) == describe(a.copy()) == describe(jnp.asarray(a))
    assert describe(a) != describe(a.T) != describe(a.astype(np.float32))
    b = a.copy()
    b[1, 2] += 1e-12
    assert describe(a) != describe(b)  # by the bytes, not a rounded print
    assert describe(Huber(1.0)) != describe(Huber(2.0))
    assert describe(SE2.between).startswith("function:lieax.")


@pytest.mark.parametrize(
    "value",
    [lambda x: x, object(), type("Local", (), {}), np.frompyfunc(abs, 1, 1)],
    ids=["user function", "object", "user class", "ufunc"],
)
def test_describe_refuses_what_it_cannot_name(value):
    with pytest.raises(Undescribable):
        describe(value)


def test_stable_repr_refuses_addresses():
    assert stable_repr((1, "x")) == "(1, 'x')"
    with pytest.raises(Undescribable):
        stable_repr((1, object()))


def test_jaxpr_fingerprint_follows_the_computation_and_its_constants():
    x = jnp.ones(3)
    assert _jaxpr(lambda x: x * 2.0, x) == _jaxpr(lambda y: y * 2.0, x)
    assert _jaxpr(lambda x: x * 2.0, x) != _jaxpr(lambda x: x * 2.5, x)
    assert _jaxpr(lambda x: x * 2.0, x) != _jaxpr(lambda x: x * 2.0, jnp.ones(4))
    c, d = np.arange(3.0), np.arange(3.0) + 1e-15
    assert _jaxpr(lambda x: x + c, x) != _jaxpr(lambda x: x + d, x)  # a captured array
    # the groups' derivative rules are lieax's: named by the source digest
    _jaxpr(lambda x: SE2.exp(x).log(), x)


def test_jaxpr_fingerprint_refuses_callbacks_and_foreign_derivative_rules():
    x = jnp.ones(3)
    callback = lambda x: jax.pure_callback(np.sin, jax.ShapeDtypeStruct(x.shape, x.dtype), x)
    with pytest.raises(Undescribable):
        _jaxpr(callback, x)

    @jax.custom_jvp
    def f(x):
        return jnp.sin(x)

    f.defjvp(lambda primals, tangents: (f(*primals), 2.0 * tangents[0]))  # its body is unseen
    with pytest.raises(Undescribable):
        _jaxpr(f, x)


@pytest.fixture
def store(tmp_path):
    _executable_store.enable(tmp_path)
    yield tmp_path
    _executable_store.disable()


def test_a_program_is_stored_loaded_and_bypassed_while_jax_checks(store):
    double = lambda x: 2.0 * x
    make = lambda: _executable_store.jit(double, fingerprint=lambda: "test: 2 x")
    first, second = make(), make()
    x = np.arange(3.0)
    np.testing.assert_array_equal(first(x), 2.0 * x)
    assert first._cache_size() == 1 and len(list(store.glob("*.bin"))) == 1
    np.testing.assert_array_equal(second(x), 2.0 * x)
    assert second._cache_size() == 0  # loaded from the file
    with jax.debug_nans(True):  # JAX's check after the call: its own jit, not a loaded program
        third = make()
        third(x)
        assert third._cache_size() == 1
    unnamed = _executable_store.jit(double)  # a function outside lieax needs a fingerprint
    unnamed(x)
    broken = _executable_store.jit(double, fingerprint=lambda: 1 / 0)  # runs as without a store
    np.testing.assert_array_equal(broken(x), 2.0 * x)
    assert len(list(store.glob("*.bin"))) == 1


def test_a_signature_reads_shapes_dtypes_and_weak_types(monkeypatch):
    x, weak = jnp.ones(3), jnp.asarray(1.0)
    for one_device in (True, False):  # with several devices, each leaf's device is checked
        monkeypatch.setattr(_executable_store, "_one_device", lambda one=one_device: one)
        avals = _executable_store._avals([x, np.ones(3), weak, np.float64(1.0), 1.0, True])
        assert avals[0] == avals[1] == ((3,), np.dtype("float64"), False)
        assert avals[2] == ((), np.dtype("float64"), True) != avals[3]
        assert avals[4:] == (((), "float", True), ((), "bool", True))
        assert _executable_store._avals([x, "text"]) is None  # not an array: not served
    traced = []
    jax.jit(lambda x: traced.append(_executable_store._avals([x])) or x)(x)
    assert traced == [None]  # a tracer: not served


def _graph(offset):
    rng = np.random.default_rng(0)
    poses = Var(SE2.exp(0.1 * rng.normal(size=(6, 3))), name="poses")
    anchor = lambda x: x.rminus(SE2.from_xy_theta(offset, 0.0, 0.0))
    between = lambda a, b, z: a.between(b).rminus(z)
    z = SE2.exp(0.1 * rng.normal(size=(5, 3)))
    return FactorGraph(
        [
            Factor(anchor, (poses[[0]],), name="anchor"),
            Factor(between, (poses[np.arange(5)], poses[np.arange(1, 6)]), z),
        ]
    )


def test_a_loop_fingerprint_names_the_residuals_structure_and_options():
    options = {"method": "dense", "schur": None, "verbose": False}
    fingerprint = lambda graph, **change: loop_fingerprint(graph, {**options, **change})
    assert fingerprint(_graph(1.0)) == fingerprint(_graph(1.0))  # rebuilt: the same loop
    assert fingerprint(_graph(1.0)) != fingerprint(_graph(1.5))  # a constant of a residual
    assert fingerprint(_graph(1.0)) != fingerprint(_graph(1.0), method="cholesky")
    # a user's retraction is not lieax's code: not named, so not stored
    with pytest.raises(Undescribable):
        fingerprint(_graph(1.0), retraction=lambda x, d: x)


CHILD = textwrap.dedent(
    """
    import sys, jax
    jax.config.update("jax_enable_x64", True)
    import numpy as np, lieax
    from lieax import SE2
    from lieax.factorgraph import Factor, FactorGraph, Var
    if sys.argv[3] == "jax":  # JAX's cache alone, as a user may have set it
        jax.config.update("jax_compilation_cache_dir", sys.argv[1])
        jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
        jax.config.update("jax_persistent_cache_min_entry_size_bytes", -1)
    else:
        lieax.enable_compilation_cache(sys.argv[1])
    if sys.argv[3] == "slow":  # a Cholesky analysis still running when a loaded loop is called
        import time
        from lieax.factorgraph._multifrontal import CholeskyPlan
        analyze = CholeskyPlan.analyze.__func__
        CholeskyPlan.analyze = classmethod(lambda *a, **k: time.sleep(1) or analyze(*a, **k))
    if sys.argv[3] == "stale":  # the store as it was before `_fresh`: JAX's copy serialized
        import contextlib
        from lieax import _executable_store
        _executable_store._fresh = lambda: contextlib.nullcontext(True)
    offset = float(sys.argv[2])
    events = []  # a program read from JAX's cache also reports a backend compilation
    jax.monitoring.register_event_listener(lambda event, **kw: events.append(event))
    jax.monitoring.register_event_duration_secs_listener(
        lambda event, seconds, **kw: events.append((event, kw.get("fun_name")))
    )
    rng = np.random.default_rng(0)
    n = 10
    truth = SE2.exp(rng.normal(size=(n, 3)))
    i, j = np.arange(n - 1), np.arange(1, n)
    poses = Var(truth.rplus(0.1 * rng.normal(size=(n, 3))), name="poses")
    anchor = lambda x: x.rminus(SE2.from_xy_theta(offset, 0.0, 0.0))  # a constant of the trace
    between = lambda a, b, z: a.between(b).rminus(z)
    graph = FactorGraph([Factor(anchor, (poses[[0]],)),
                         Factor(between, (poses[i], poses[j]), truth[i].between(truth[j]))])
    solved = graph.solve(linear_solver="cholesky")
    assert solved.converged
    assert np.allclose(solved.values[0].parameters()[0, 2:], [offset, 0.0], atol=1e-9)
    values = np.asarray(solved.values[0].parameters())
    compiled = sum(e[0] == "/jax/core/compile/backend_compile_duration" for e in events)
    compiled -= events.count("/jax/compilation_cache/cache_hits")
    loops = events.count(("/jax/core/compile/jaxpr_trace_duration", "loop"))
    print(loops, compiled, values.tobytes().hex())
    """
)


def test_a_second_process_loads_the_loop_and_a_changed_residual_compiles_its_own(tmp_path):
    """1. A process with JAX's persistent cache alone fills it. 2. One with lieax's store whose
    compilation reads JAX's copy (as the store did before `_fresh`) writes a program without
    its kernels. 3. The next loads it, its first run fails with NOT_FOUND, and the store
    compiles afresh (not from JAX's cache) and writes the file again, with the same bits. 4.
    The next does not trace the loop, compiles nothing and returns the same bits (the native
    Cholesky's custom call and jaxlib's LAPACK kernels prepared before loading, its plan
    waited for though its analysis is slowed down). 5. One whose
    residual differs only in a constant traces and compiles its own loop and solves its own
    problem (its child asserts the solution). ICP's and GICP's loops: test_native_kdtree."""
    run = lambda offset, cache="both": child_output(CHILD, tmp_path, offset, cache).split()[-3:]
    traced, compiled, values = run(0.5, "jax")
    assert traced == "1" and int(compiled) > 0
    assert run(0.5, "stale")[::2] == ["1", values]
    assert len(list((tmp_path / "lieax-programs").glob("*.bin"))) == 1
    traced, _, again = run(0.5)
    assert traced == "1" and again == values
    assert run(0.5, "slow") == ["0", "0", values]  # not traced: loaded; waited for its plan
    traced, compiled, other = run(0.75)
    assert traced == "1" and int(compiled) > 0 and other != values
