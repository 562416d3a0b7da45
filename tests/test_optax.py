"""Tests of lieax.optax: first-order optimization on manifolds reaches the least-squares optimum."""

import functools

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest

jax.config.update("jax_enable_x64", True)

import lieax  # noqa: E402
import lieax.lstsq  # noqa: E402
import lieax.optax  # noqa: E402


def residual(x, data):
    """A rigid alignment over a mixed pytree: `{"rotation": SO3, "translation": (3,)}`."""
    source, target = data
    return jax.vmap(lambda p, q: x["rotation"] @ p + x["translation"] - q)(source, target)


def loss(x, data):
    return 0.5 * jnp.sum(residual(x, data) ** 2)


@functools.cache
def data():
    k1, k2 = jax.random.split(jax.random.PRNGKey(0))
    source = jax.random.normal(k1, (30, 3))
    rotation = lieax.SO3.exp(jnp.array([0.3, -1.0, 2.0]))
    target = rotation @ source + jnp.array([1.0, 2.0, 3.0]) + 0.02 * jax.random.normal(k2, (30, 3))
    return source, target


START = {"rotation": lieax.SO3.identity(dtype=jnp.float64), "translation": jnp.zeros(3)}
ADAM = optax.adam(optax.exponential_decay(0.1, transition_steps=200, decay_rate=0.5))


@pytest.fixture(scope="module")
def lm_optimum():
    return lieax.lstsq.least_squares(residual, START, data()).value


def assert_same_point(x, y, atol):
    np.testing.assert_allclose(x["rotation"].as_matrix(), y["rotation"].as_matrix(), atol=atol)
    np.testing.assert_allclose(x["translation"], y["translation"], atol=atol)


def test_adam_reaches_the_lm_optimum(lm_optimum):
    result = lieax.optax.minimize(loss, START, ADAM, 2000, data())
    assert isinstance(result.value["rotation"], lieax.SO3)
    assert result.loss_history.shape == (2001,) and result.loss_history[0] > result.loss
    assert_same_point(result.value, lm_optimum, atol=1e-7)
    np.testing.assert_allclose(result.loss, loss(lm_optimum, data()), rtol=1e-10)


def test_lbfgs_line_search_on_the_manifold(lm_optimum):
    """optax.lbfgs evaluates `value_fn` at trial points: they are re-expressed on the manifold."""
    result = lieax.optax.minimize(loss, START, optax.lbfgs(), 60, data())
    assert_same_point(result.value, lm_optimum, atol=1e-8)


def test_on_manifold_in_a_user_loop(lm_optimum):
    inner = optax.chain(optax.add_decayed_weights(0.0), optax.sgd(0.01, momentum=0.9))
    optimizer = lieax.optax.on_manifold(inner)

    @jax.jit
    def step(x, state):
        value, grad = lieax.value_and_grad(loss)(x, data())
        updates, state = optimizer.update(grad, state, x)
        return lieax.optax.apply_updates(x, updates), state, value

    x, state = START, optimizer.init(START)
    tangent_state = inner.init(lieax.zero_tangents(START))  # the state lives in tangent space
    assert jax.tree_util.tree_structure(state) == jax.tree_util.tree_structure(tangent_state)
    values = []
    for _ in range(300):
        x, state, value = step(x, state)
        values.append(float(value))
    assert values[-1] < 1e-3 * values[0]
    assert_same_point(x, lm_optimum, atol=1e-6)
    np.testing.assert_allclose(jnp.linalg.norm(x["rotation"].parameters()), 1.0, atol=1e-12)


def test_apply_updates_is_the_retraction():
    x = {"rotation": lieax.SO3.exp(jnp.array([0.1, 0.2, 0.3])), "translation": jnp.ones(3)}
    updates = {"rotation": jnp.array([0.0, 0.5, -0.1]), "translation": jnp.arange(3.0)}
    moved = lieax.optax.apply_updates(x, updates)
    np.testing.assert_allclose(
        moved["rotation"].parameters(), x["rotation"].rplus(updates["rotation"]).parameters()
    )
    np.testing.assert_allclose(moved["translation"], [1.0, 2.0, 3.0])
    single = lieax.optax.apply_updates(lieax.SO3.identity(dtype=jnp.float32), jnp.ones(3))
    assert single.parameters().dtype == jnp.float32
