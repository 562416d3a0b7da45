"""Tests of what the solvers share (issue 15): one `Status` enum, one `SolverResult` base of the
result types (`status_name`, `converged`, a one-line `repr`) and one `SolveError` base of their
errors, for `lieax.lstsq`, `lieax.factorgraph`, `lieax.graph` and `lieax.icp`.

Every solve here is small: compiling the loops dominates the cost.
"""

import re

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import lieax
from lieax import SE2, icp, lstsq
from lieax import graph as lg
from lieax.factorgraph import Factor, FactorGraph, SolveResult, Var
from lieax.lstsq._solution import is_failure

jax.config.update("jax_enable_x64", True)

FLOAT = r"-?[0-9.]+(?:e[-+][0-9]+)?"


def line(patterns):
    """A regular expression of a one-line repr: the class, then `name=value` fields."""
    return re.compile(r"^(\w+)\(" + ", ".join(patterns) + r"\)$")


def fields(text):
    """The `name=value` pairs of a one-line repr, as strings."""
    return dict(re.findall(r"(\w+)=([^,()]+)", text))


# ---- one status enum, one error base -------------------------------------------------------------


def test_one_status_enum_with_fixed_codes():
    assert icp.Status is lstsq.Status is lieax.Status
    codes = {member.name: int(member) for member in lstsq.Status}
    assert codes == {
        "RUNNING": -1,
        "CONVERGED": 0,
        "MAX_ITERATIONS": 1,
        "DIVERGED": 2,
        "NONFINITE": 3,
        "DEGENERATE": 4,
        "INVALID": 5,
    }
    failures = {member.name for member in lstsq.Status if is_failure(member)}
    assert failures == {"DIVERGED", "NONFINITE", "DEGENERATE", "INVALID"}


def test_one_error_base():
    assert lieax.SolveError is lstsq.SolveError
    assert issubclass(icp.ICPError, lstsq.SolveError)
    assert issubclass(icp.ICPInputError, icp.ICPError) and issubclass(icp.ICPInputError, ValueError)
    assert issubclass(lstsq.NonFiniteStartError, lstsq.SolveError)
    assert issubclass(lstsq.SolveError, RuntimeError)


def test_every_result_type_is_a_solver_result():
    for cls in (lstsq.Solution, SolveResult, lg.OptimizeResult, icp.ICPResult):
        assert issubclass(cls, lieax.SolverResult), cls
    # the field names users read are unchanged
    assert lstsq.Solution._fields == ("value", "cost", "iterations", "status", "cost_history")
    assert SolveResult._fields == (
        "values", "cost", "iterations", "linear_solves", "status", "cost_history", "damping",
    )  # fmt: skip
    assert icp.ICPResult._fields == (
        "transform", "fitness", "inlier_rmse", "iterations", "status", "correspondences",
    )  # fmt: skip
    assert [f.name for f in lg.OptimizeResult.__dataclass_fields__.values()] == [
        "poses", "cost", "iterations", "linear_solves", "status", "cost_history", "damping",
    ]  # fmt: skip


# ---- least squares --------------------------------------------------------------------------------


def exponential(x, t):
    return jnp.exp(x[0] * t) - jnp.exp(0.3 * t)


def test_solution_status_repr_and_pytree():
    t = jnp.linspace(0.0, 1.0, 5)
    solution = lstsq.least_squares(exponential, jnp.zeros(1), t)
    assert solution.status_name == "CONVERGED" and bool(solution.converged)
    text = repr(solution)
    assert line([r"status=CONVERGED", rf"cost={FLOAT}", r"iterations=\d+"]).match(text), text
    assert int(fields(text)["iterations"]) == int(solution.iterations)
    assert float(fields(text)["cost"]) == pytest.approx(float(solution.cost), rel=1e-9, abs=1e-30)
    assert not hasattr(solution, "__dict__")  # a NamedTuple still (slots only)
    leaves, treedef = jax.tree.flatten(solution)
    again = jax.tree.unflatten(treedef, leaves)
    assert type(again) is lstsq.Solution and type(solution._replace(cost=0.0)) is lstsq.Solution

    stopped = lstsq.least_squares(
        exponential, jnp.array([5.0]), t, termination=lstsq.Termination(max_iterations=1)
    )
    assert stopped.status_name == "MAX_ITERATIONS" and not bool(stopped.converged)
    assert repr(stopped).startswith("Solution(status=MAX_ITERATIONS, ")


def test_batched_and_traced_reprs():
    t = jnp.linspace(0.0, 1.0, 5)
    starts = jnp.array([[0.0], [jnp.nan], [0.1]])
    solve = jax.vmap(lambda x0: lstsq.least_squares(exponential, x0, t, throw=False))
    batch = solve(starts)
    assert list(batch.status_name) == ["CONVERGED", "NONFINITE", "CONVERGED"]
    assert list(np.asarray(batch.converged)) == [True, False, True]
    assert repr(batch) == "Solution(batch of shape (3,): CONVERGED x2, NONFINITE x1)"
    seen = []

    @jax.jit
    def traced(x0):
        solution = lstsq.least_squares(exponential, x0, t)
        seen.append(repr(solution))
        return solution.converged

    assert bool(traced(jnp.zeros(1)))
    assert re.match(r"^Solution\(status=\w*Tracer\(int32\[\]\), \.\.\.\)$", seen[0]), seen[0]


# ---- factor graph and pose graph ------------------------------------------------------------------


def small_chain(n=6, seed=0):
    rng = np.random.default_rng(seed)
    xi = rng.normal(size=(n, 3)) * 0.3
    xi[:, 0] += np.arange(n)
    truth = SE2.exp(jnp.asarray(xi))
    i, j = np.arange(n - 1), np.arange(1, n)
    measured = truth[i].between(truth[j]).rplus(jnp.asarray(rng.normal(size=(n - 1, 3)) * 0.05))
    start = truth.rplus(jnp.asarray(rng.normal(size=(n, 3)) * 0.1).at[0].set(0.0))
    return truth, i, j, measured, start


def test_factor_graph_result_status_and_repr():
    _, i, j, measured, start = small_chain()
    poses = Var(start, fixed=[0], name="poses")
    graph = FactorGraph(
        [Factor(lambda a, b, z: z.between(a.between(b)).log(), (poses[i], poses[j]), measured)]
    )
    result = graph.solve()
    assert result.status_name == "CONVERGED" and bool(result.converged)
    text = repr(result)
    pattern = line(
        [r"status=CONVERGED", rf"cost={FLOAT}", r"iterations=\d+", r"linear_solves=\d+",
         rf"damping={FLOAT}"]
    )  # fmt: skip
    assert pattern.match(text), text
    shown = fields(text)
    assert int(shown["linear_solves"]) == int(result.linear_solves)
    assert float(shown["damping"]) == pytest.approx(float(result.damping), rel=1e-9)


def test_optimize_result_status_and_repr():
    _, i, j, measured, start = small_chain()
    graph = lg.PoseGraph.create(start, np.stack([i, j], 1), measured, np.eye(3) * 100.0)
    result = lg.optimize(graph)
    assert result.status is lstsq.Status.CONVERGED and result.converged is True
    assert result.status_name == "CONVERGED"
    text = repr(result)
    pattern = line(
        [r"status=CONVERGED", rf"cost={FLOAT}", r"iterations=\d+", r"linear_solves=\d+",
         rf"damping={FLOAT}"]
    )  # fmt: skip
    assert pattern.match(text), text
    assert int(fields(text)["iterations"]) == result.iterations


# ---- ICP -----------------------------------------------------------------------------------------


def test_icp_result_status_repr_and_errors():
    source, target, _, _ = icp.synthetic_pair(120, rotation_deg=5.0, translation=0.05, seed=1)
    result = icp.point_to_point(source, target, max_correspondence_distance=0.4)
    assert result.status_name == "CONVERGED" and bool(result.converged)
    text = repr(result)
    pattern = line(
        [r"status=CONVERGED", rf"fitness={FLOAT}", rf"inlier_rmse={FLOAT}", r"iterations=\d+"]
    )
    assert pattern.match(text), text
    assert float(fields(text)["fitness"]) == pytest.approx(float(result.fitness), rel=1e-9)
    # a degenerate run is a SolveError (ICPError), NaN input a ValueError too
    with pytest.raises(lstsq.SolveError, match="degenerate") as error:
        icp.point_to_point(source, target + 50.0, max_correspondence_distance=0.4)
    assert type(error.value) is icp.ICPError
    with pytest.raises(ValueError, match="not finite") as error:
        icp.point_to_point(source, target.at[3].set(jnp.nan), max_correspondence_distance=0.4)
    assert isinstance(error.value, lstsq.SolveError)
    far = icp.point_to_point(source, target + 50.0, max_correspondence_distance=0.4, throw=False)
    assert far.status == icp.Status.DEGENERATE and far.status_name == "DEGENERATE"
    assert repr(far).startswith("ICPResult(status=DEGENERATE, fitness=0, ")
