"""`lieax._cpu_emitters`: the point-cloud programs compile with XLA's classic CPU fusion emitters
(the factor-graph loop also with single-threaded dots) where this XLA knows the options, and with
XLA's defaults where it does not, to the same results."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from lieax import _cpu_emitters, icp


@pytest.fixture
def unknown_option(monkeypatch):
    """An XLA that does not know the option (a name no XLA has)."""
    monkeypatch.setattr(_cpu_emitters, "CLASSIC_CPU_EMITTERS", {"xla_lieax_no_such_option": 1})
    monkeypatch.setattr(_cpu_emitters, "_REFUSED", set())


def test_this_xla_knows_the_options():
    # The faster programs are the ones CI measures; if an XLA upgrade drops an option, this says so.
    _cpu_emitters.jit(lambda x: x + 1)(jnp.arange(2.0))
    assert _cpu_emitters.known()
    solver_like = _cpu_emitters.jit(
        lambda a, b: a @ b, options=_cpu_emitters.SOLVER_LOOP_OPTIONS
    )  # (the factor-graph loop's options: single-threaded dots too)
    a = jnp.arange(24.0).reshape(2, 3, 4)
    np.testing.assert_allclose(solver_like(a, a.swapaxes(1, 2)), a @ a.swapaxes(1, 2), rtol=1e-12)
    assert not _cpu_emitters._REFUSED
    assert solver_like._cache_size() == 1  # compiled with the options, not the fallback


def test_a_program_with_an_unknown_option_of_its_own_falls_back_alone(monkeypatch):
    monkeypatch.setattr(_cpu_emitters, "_REFUSED", set())
    own = _cpu_emitters.jit(lambda x: x - 1, options={"xla_lieax_no_such_option": 1})
    np.testing.assert_array_equal(own(jnp.arange(2.0)), [-1.0, 0.0])
    assert _cpu_emitters._REFUSED == {"xla_lieax_no_such_option"}
    assert _cpu_emitters.known()  # the other programs keep the classic emitters
    assert own(jnp.arange(2.0)).tolist() == [-1.0, 0.0] and own._cache_size() == 1


def test_an_unknown_option_falls_back_to_the_defaults(unknown_option):
    double = _cpu_emitters.jit(lambda x: 2 * x)
    np.testing.assert_array_equal(double(jnp.arange(3.0)), [0.0, 2.0, 4.0])
    assert not _cpu_emitters.known()  # the first compilation found out
    assert double._cache_size() == 1
    triple = _cpu_emitters.jit(lambda x: 3 * x)  # later programs go straight to the defaults
    np.testing.assert_array_equal(triple(jnp.arange(3.0)), [0.0, 3.0, 6.0])
    assert triple._cache_size() == 1


def test_a_runtime_error_of_the_program_is_not_taken_for_a_refusal():
    def fail(x):
        raise RuntimeError("a failure inside the program")

    failing = _cpu_emitters.jit(
        lambda x: jax.pure_callback(fail, jax.ShapeDtypeStruct((), jnp.float32), x)
    )
    with pytest.raises(Exception, match="a failure inside the program"):
        failing(jnp.float32(1.0))
    assert _cpu_emitters.known()


def test_both_variants_compile_once_and_agree(monkeypatch):
    @_cpu_emitters.jit(static_argnames=("power",))
    def moment(x, power):
        return jnp.sum(jnp.sin(x) ** power)

    x = jnp.linspace(0.0, 3.0, 1000)
    classic = moment(x, power=3)
    assert moment._cache_size() == 1
    monkeypatch.setattr(_cpu_emitters, "known", lambda: False)
    default = moment(x, power=3)
    assert moment._cache_size() == 2
    np.testing.assert_allclose(classic, default, rtol=1e-12)
    np.testing.assert_allclose(classic, np.sum(np.sin(np.asarray(x)) ** 3), rtol=1e-12)


def test_icp_registers_alike_with_either_emitters(monkeypatch):
    source, target, normals, _ = icp.synthetic_pair(600, rotation_deg=8.0, translation=0.05, seed=3)

    def register():
        return icp.point_to_plane(
            source, target, target_normals=normals, max_correspondence_distance=0.3
        )

    classic = register()
    monkeypatch.setattr(_cpu_emitters, "known", lambda: False)
    default = register()
    assert classic.status_name == default.status_name == "CONVERGED"
    assert int(classic.iterations) == int(default.iterations)
    gap = (classic.transform.inverse() @ default.transform).log()
    assert float(jnp.max(jnp.abs(gap))) < 1e-9
    assert jax.numpy.array_equal(classic.correspondences, default.correspondences)


def test_a_staged_or_transformed_program_takes_the_defaults():
    # (JAX refuses compile options on a nested jit; the enclosing program's options apply)
    double = _cpu_emitters.jit(lambda x: 2 * x)
    assert jax.grad(lambda x: jnp.sum(double(x)))(jnp.ones(3)).tolist() == [2.0, 2.0, 2.0]
    assert jax.jacfwd(double)(jnp.ones(2)).tolist() == [[2.0, 0.0], [0.0, 2.0]]
    np.testing.assert_array_equal(jax.jit(double)(jnp.arange(3.0)), [0.0, 2.0, 4.0])
    np.testing.assert_array_equal(jax.jit(jax.vmap(double))(jnp.ones((2, 3))), 2 * np.ones((2, 3)))
    np.testing.assert_array_equal(jax.vmap(double)(jnp.ones((2, 3))), 2 * np.ones((2, 3)))
    looped = jax.lax.fori_loop(0, 3, lambda i, x: double(x), jnp.ones(2))
    np.testing.assert_array_equal(looped, [8.0, 8.0])
