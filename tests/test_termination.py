"""`lieax.lstsq.Termination`, the one stopping-rule object of both doors: its tolerances are
traced (a new value reuses the compiled solve of `least_squares` and the loop of
`FactorGraph.solve`), its fields are checked, and each door refuses, naming the option, what it
does not run. The comparisons the peers differ in (`>=` or `>`) are options of
`LevenbergMarquardt`, and `GaussNewton`'s `divergence_factor` is honoured by both doors."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

jax.config.update("jax_enable_x64", True)

from test_first_call import compilations  # noqa: E402

import lieax.lstsq as ls  # noqa: E402
from lieax.factorgraph import Factor, FactorGraph, Var  # noqa: E402
from lieax.lstsq import _least_squares  # noqa: E402

TRACES = []
START = np.array([-1.2, 1.0])


def rosenbrock(x, data):
    """Rosenbrock's residual (Gauss-Newton's first step from `START` raises the cost 100-fold)."""
    TRACES.append(None)
    return data[0] * jnp.stack([10.0 * (x[1] - x[0] ** 2), 1.0 - x[0]])


def rosenbrock_factor(x, scale):
    TRACES.append(None)
    return scale[0] * jnp.stack([10.0 * (x[1] - x[0] ** 2), 1.0 - x[0]])


@pytest.fixture(scope="module")
def graph():
    x = Var(jnp.asarray(START)[None], name="x")
    return FactorGraph([Factor(rosenbrock_factor, (x[np.array([0])],), jnp.ones((1, 1)))],
                       check_gauge=False)  # fmt: skip


def test_a_new_tolerance_reuses_the_compiled_least_squares():
    """Two tolerances, one trace and one compilation (XLA programs counted as
    `test_first_call` counts them); the looser stops earlier. Under `jit` the tolerance may be
    traced."""
    data, start = (jnp.ones(()),), jnp.asarray(START)
    loose_termination = ls.Termination(function_tolerance=0.3)
    tight = ls.least_squares(rosenbrock, start, data)
    traced, cached = len(TRACES), _least_squares._solve._cache_size()
    with compilations() as compiled:
        loose = ls.least_squares(rosenbrock, start, data, termination=loose_termination)
    assert compiled == []
    assert (len(TRACES), _least_squares._solve._cache_size()) == (traced, cached)
    assert tight.converged and loose.converged
    assert int(loose.iterations) < int(tight.iterations)

    @jax.jit
    def solve(tolerance):
        termination = ls.Termination(function_tolerance=tolerance)
        return ls.least_squares(rosenbrock, jnp.asarray(START), data, termination=termination)

    assert int(solve(0.3).iterations) == int(loose.iterations)


def test_a_new_tolerance_reuses_the_graph_loop(graph):
    loose_termination = ls.Termination.gtsam(function_tolerance=0.3, max_iterations=90)
    tight = graph.solve(termination=ls.Termination.gtsam(function_tolerance=1e-12))
    loops, traced = dict(graph._loops), len(TRACES)
    with compilations() as compiled:  # a new limit of the same power of two too
        loose = graph.solve(termination=loose_termination)
    assert compiled == []
    assert graph._loops == loops and len(TRACES) == traced
    assert tight.converged and loose.converged
    assert int(loose.iterations) < int(tight.iterations)


def test_termination_checks_its_fields():
    for bad in (-1, 2.5, "3", np.float64(2.0)):
        with pytest.raises(ValueError, match="max_iterations must be a non-negative int"):
            ls.Termination(max_iterations=bad)
    assert ls.Termination(max_iterations=np.int64(7)).max_iterations == 7
    with pytest.raises(ValueError, match="counting must be one of"):
        ls.Termination(counting="linearizations")
    for name in ("function_tolerance", "absolute_function_tolerance", "gradient_tolerance",
                 "parameter_tolerance"):  # fmt: skip
        with pytest.raises(ValueError, match=f"{name} must be non-negative"):
            ls.Termination(**{name: -1e-3})
    with pytest.raises(TypeError, match="termination must be a lieax.lstsq.Termination"):
        ls.least_squares(rosenbrock, START, (1.0,), termination=100)


def test_each_door_refuses_what_it_does_not_run(graph):
    """The refusals come before anything is compiled."""
    with pytest.raises(ValueError, match=r"least_squares counts .* Termination.counting='outer'"):
        ls.least_squares(rosenbrock, START, (1.0,), termination=ls.Termination.gtsam())
    with pytest.raises(ValueError, match=r"FactorGraph.solve counts .*counting='trials'"):
        graph.solve(termination=ls.Termination())
    for name in ("gradient_tolerance", "parameter_tolerance"):
        with pytest.raises(ValueError, match=f"no such test: Termination.{name} must be 0"):
            graph.solve(termination=ls.Termination.gtsam(**{name: 1e-8}))
    with pytest.raises(ValueError, match="needs a value of Termination.function_tolerance"):
        graph.solve(termination=ls.Termination.gtsam(function_tolerance=None))


def test_the_comparisons_are_options():
    r"""A step whose gain ratio equals `min_gain_ratio` is kept with `inclusive_gain_ratio`
    (MINPACK's $\ge$), rejected without (GTSAM's and Ceres' $>$); a damping equal to
    `max_damping` gives up with `inclusive_max_damping` (GTSAM's $\ge$) only."""
    one = jnp.ones(())
    for solver, accepted in ((ls.LevenbergMarquardt(), True), (ls.LevenbergMarquardt.ceres(), False),
                             (ls.LevenbergMarquardt.gtsam(), False),
                             (ls.LevenbergMarquardt.gtsam(inclusive_gain_ratio=True), True)):  # fmt: skip
        state = solver.init(2, jnp.float64)
        accept, _ = solver.update(state, jnp.asarray(solver.min_gain_ratio), True, one, one)
        assert bool(accept) is accepted, solver
    for solver, gives_up in ((ls.LevenbergMarquardt.gtsam(), True),
                             (ls.LevenbergMarquardt.ceres(), False)):  # fmt: skip
        state = (jnp.asarray(solver.max_damping), *solver.init(2, jnp.float64)[1:])
        assert bool(solver.diverged(state, one, one)) is gives_up, solver


def test_gauss_newton_divergence_factor_in_both_doors(graph):
    """Gauss-Newton's first step from Rosenbrock's start raises the cost 100-fold: with
    `divergence_factor=10` both doors stop `DIVERGED`, with the default both converge."""
    termination = ls.Termination.gtsam(function_tolerance=1e-12)
    for factor, status in ((10.0, ls.Status.DIVERGED), (1e6, ls.Status.CONVERGED)):
        solver = ls.GaussNewton(divergence_factor=factor)
        dense = ls.least_squares(rosenbrock, START, (1.0,), solver=solver, throw=False)
        sparse = graph.solve(solver=solver, termination=termination, throw=False)
        assert int(dense.status) == int(sparse.status) == status
