"""`lieax._host_call`: the primitive path and the `pure_callback` fallback give the same results
under `jit`, `vmap` and inside a loop, and the guard accepts exactly the JAX internals the
primitive's lowering relies on."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from lieax import _host_call

PATHS = {"primitive": _host_call.host_call, "pure_callback": _host_call.pure_callback_host_call}


def _host_solve(matrix, rhs):
    assert isinstance(matrix, np.ndarray) and isinstance(rhs, np.ndarray)
    return np.linalg.solve(matrix, rhs)


def _solve(call, matrix, rhs):
    return call(_host_solve, jax.ShapeDtypeStruct(rhs.shape, rhs.dtype), matrix, rhs)


@pytest.fixture(scope="module")
def problem():
    rng = np.random.default_rng(0)
    a = rng.normal(size=(5, 3, 3))
    matrices = a @ np.swapaxes(a, -1, -2) + 3 * np.eye(3)
    return jnp.asarray(matrices), jnp.asarray(rng.normal(size=(5, 3)))


def test_this_jax_has_the_primitive_path():
    # The fast path is the one CI exercises; if a JAX upgrade removes it, this says so.
    assert _host_call._HOST_CALL is not None


@pytest.mark.parametrize("path", PATHS)
def test_jit_vmap_and_loop_agree_with_numpy(problem, path):
    call = PATHS[path]
    matrices, rhs = problem
    expected = np.linalg.solve(np.asarray(matrices), np.asarray(rhs)[..., None])[..., 0]
    single = jax.jit(lambda m, b: _solve(call, m, b))(matrices[0], rhs[0])
    np.testing.assert_allclose(single, expected[0], rtol=1e-12)
    batched = jax.jit(jax.vmap(lambda m, b: _solve(call, m, b)))(matrices, rhs)
    np.testing.assert_allclose(batched, expected, rtol=1e-12)

    def body(i, x):  # x <- A⁻¹ x three times, on the host inside a fori_loop
        return _solve(call, matrices[0], x)

    looped = jax.jit(lambda x: jax.lax.fori_loop(0, 3, body, x))(rhs[0])
    m = np.asarray(matrices[0])
    np.testing.assert_allclose(looped, np.linalg.solve(m @ m @ m, np.asarray(rhs[0])), rtol=1e-10)


def test_guard_checks_the_keywords_the_lowering_passes():
    def current(
        ctx, callback, token, operands, avals_in, avals_out, *, has_side_effect, returns_token=True
    ):
        pass

    def older(ctx, callback, token, operands, avals_in, avals_out, has_side_effect):
        pass

    assert _host_call._primitive_supported(current)
    assert not _host_call._primitive_supported(older)
    from jax._src.callback import emit_python_callback

    assert _host_call._primitive_supported(emit_python_callback)


def _host_solve_batch(matrices, rhs):
    assert matrices.ndim == 3 and rhs.ndim == 2  # one call with the batch axis first
    _host_solve_batch.calls += 1
    return np.linalg.solve(matrices, rhs[..., None])[..., 0]


@pytest.mark.parametrize("path", PATHS)
def test_batched_host_function_is_called_once_for_a_batch(problem, path):
    """`batched=`: under `vmap` and nested `vmap`, one call with the batch axes flattened into
    one, the results those of the element function; an unbatched operand is broadcast."""
    call = PATHS[path]
    matrices, rhs = problem
    expected = np.linalg.solve(np.asarray(matrices), np.asarray(rhs)[..., None])[..., 0]

    def solve(m, b):
        result = jax.ShapeDtypeStruct(b.shape, b.dtype)
        return call(_host_solve, result, m, b, batched=_host_solve_batch)

    _host_solve_batch.calls = 0
    batched = jax.jit(jax.vmap(solve))(matrices, rhs)
    np.testing.assert_allclose(batched, expected, rtol=1e-12)
    assert _host_solve_batch.calls == 1
    shared = jax.jit(jax.vmap(solve, in_axes=(None, 0)))(matrices[0], rhs)
    np.testing.assert_allclose(
        shared, np.linalg.solve(np.asarray(matrices[0]), np.asarray(rhs).T).T, rtol=1e-12
    )
    nested = jax.jit(jax.vmap(jax.vmap(solve)))(
        jnp.stack([matrices, matrices[::-1]]), jnp.stack([rhs, rhs[::-1]])
    )
    np.testing.assert_allclose(nested, np.stack([expected, expected[::-1]]), rtol=1e-12)
    single = jax.jit(solve)(matrices[1], rhs[1])  # no vmap: the element function
    np.testing.assert_allclose(single, expected[1], rtol=1e-12)
