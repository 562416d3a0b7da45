"""`lieax._runtime_error.raise_if`: raises at run time under `jit`, reports under `vmap`, and lets
derivatives through."""

import jax
import jax.numpy as jnp
import pytest

from lieax._runtime_error import raise_if

FAILED = 3


def _solve(x):
    """A stand-in for a solver: a value and an integer status (FAILED where x > 0)."""
    status = jnp.where(x > 0, FAILED, 1).astype(jnp.int32)
    status = raise_if(status, lambda code: code == FAILED, lambda code: ValueError(f"ended {code}"))
    return 2.0 * x, status


def test_jit_raises_only_on_failure():
    value, status = jax.jit(_solve)(-1.0)
    assert float(value) == -2.0 and int(status) == 1
    with pytest.raises(Exception, match="ValueError: ended 3"):
        jax.block_until_ready(jax.jit(_solve)(1.0))


def test_vmap_reports_statuses_instead():
    values, statuses = jax.jit(jax.vmap(_solve))(jnp.array([1.0, -1.0]))
    assert statuses.tolist() == [FAILED, 1] and values.tolist() == [2.0, -2.0]


def test_derivatives_pass_through():
    assert float(jax.grad(lambda x: _solve(x)[0])(-1.0)) == 2.0
    primal, tangent = jax.jvp(lambda x: _solve(x)[0], (-1.0,), (1.0,))
    assert float(tangent) == 2.0 and float(primal) == -2.0


def test_solvers_throw_under_jit_and_report_under_vmap():
    from lieax import lstsq
    from lieax.factorgraph import Factor, FactorGraph, Var

    def residual(x, a):
        return jnp.where(a > 0, jnp.nan, 1.0) * (x - a)  # NaN residual for a > 0

    solve = jax.jit(lambda a: lstsq.least_squares(residual, jnp.zeros(2), a).status)
    assert int(solve(jnp.array([-1.0, -2.0]))) == lstsq.Status.CONVERGED
    with pytest.raises(Exception, match="SolveError: least_squares ended NONFINITE"):
        jax.block_until_ready(solve(jnp.array([1.0, 2.0])))
    batch = jax.vmap(solve)(jnp.array([[1.0, 2.0], [-1.0, -2.0]]))
    assert batch.tolist() == [lstsq.Status.NONFINITE, lstsq.Status.CONVERGED]

    x = Var(jnp.zeros((1, 2)), name="x")
    graph = FactorGraph(
        [Factor(lambda x, a: residual(x, a), (x[jnp.array([0])],), jnp.zeros((1, 2)))]
    )

    def solve_graph(a):
        return graph.solve(data=[(a[None], None, None)]).status

    assert int(jax.jit(solve_graph)(jnp.array([-1.0, -2.0]))) == lstsq.Status.CONVERGED
    with pytest.raises(Exception, match="SolveError: the factor graph solve ended NONFINITE"):
        jax.block_until_ready(jax.jit(solve_graph)(jnp.array([1.0, 2.0])))
    batch = jax.vmap(solve_graph)(jnp.array([[1.0, 2.0], [-1.0, -2.0]]))
    assert batch.tolist() == [lstsq.Status.NONFINITE, lstsq.Status.CONVERGED]
