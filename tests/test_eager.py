"""Group operations called outside `jit` compile one program each (`lieax._eager`); inside a
staged program they are inlined, so the caller's program holds no nested call."""

import jax
import jax.numpy as jnp
import numpy as np
from jax._src import monitoring

import lieax


class _Compilations:
    def __init__(self):
        self.count = 0
        monitoring.register_event_duration_secs_listener(self._on_duration)

    def _on_duration(self, event, duration, **_):
        self.count += "backend_compile" in event


COMPILATIONS = _Compilations()


def _compiled_by(fn):
    before = COMPILATIONS.count
    jax.block_until_ready(fn())
    return COMPILATIONS.count - before


def test_an_eager_group_operation_is_one_program():
    # shapes no other test uses, so that nothing is compiled already
    rng = np.random.default_rng(0)
    poses = lieax.SE3.exp(jnp.asarray(rng.normal(size=(13, 6))))
    points = jnp.asarray(rng.normal(size=(13, 3)))
    assert _compiled_by(lambda: poses @ points) == 1
    assert _compiled_by(lambda: poses @ points) == 0  # cached
    assert _compiled_by(lambda: poses.inverse().log()) == 2  # inverse, then log
    expected = np.einsum("nij,nj->ni", np.asarray(poses.as_matrix())[:, :3, :3], points)
    expected += np.asarray(poses.translation())
    np.testing.assert_allclose(poses @ points, expected, rtol=1e-12, atol=1e-12)


def test_a_staged_program_holds_no_nested_call():
    def act(params, points):
        return lieax.SE3(params) @ points

    jaxpr = jax.make_jaxpr(act)(jnp.zeros(7).at[0].set(1.0), jnp.zeros(3))
    names = {eqn.primitive.name for eqn in jaxpr.jaxpr.eqns}
    assert "pjit" not in names and "jit" not in names


def test_eager_derivatives_go_through_the_compiled_kernels():
    """Under an eager `jvp` the kernel runs compiled, with its closed-form rule: the same
    derivative as inside `jit`."""
    omega = jnp.array([0.3, -0.2, 0.1])
    direction = jnp.array([1.0, 0.5, -0.25])

    def rotate(w):
        return lieax.SO3.exp(w) @ jnp.array([1.0, 2.0, 3.0])

    eager = jax.jvp(rotate, (omega,), (direction,))
    staged = jax.jit(lambda w, d: jax.jvp(rotate, (w,), (d,)))(omega, direction)
    np.testing.assert_allclose(eager[1], staged[1], rtol=1e-13, atol=1e-13)
