"""Tests of `FactorGraph(..., buckets=True)`: a growing SE2 window with landmarks (robust losses,
per-instance information, a fixed pose) compiles its loop once per bucket (JAX's compilation
events and the loop's `_cache_size()`), each bucketed solve equals the unbucketed solve of the
same graph (values and cost), with the dense, CG and native (or host) multifrontal solvers,
under `vmap` and differentiated; the Schur complement is refused.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from _compilations import _COMPILED

from lieax import SE2
from lieax.factorgraph import Factor, FactorGraph, Var, _graph, _multifrontal, marginal_covariances
from lieax.factorgraph._buckets import bucket_size
from lieax.graph import between_error, prior_error
from lieax.lstsq import Cauchy, Huber

jax.config.update("jax_enable_x64", True)

# 10, 11 and 12 poses fall in one bucket of every count (poses and landmark sightings 12,
# odometry 12, landmarks 4, the prior 1); 13 poses cross into the poses' next bucket (16)
SIZES = (10, 11, 12, 13)
LANDMARKS = 4


def sighting(x, landmark, z):
    return (x.inverse() @ landmark) - z


def window(n, buckets, seed=0):
    """The first `n` poses of an SE2 trajectory with odometry (per-instance information, a Huber
    loss), a prior on pose 0, one sighting per pose of one of `LANDMARKS` landmarks (a Cauchy
    loss), and the middle pose fixed (which pose moves with `n`: a mask, not the structure);
    noisy measurements, a perturbed start."""
    rng = np.random.default_rng(seed)
    xi = np.c_[np.arange(n) * 1.0, np.sin(np.arange(n)), 0.1 * rng.normal(size=n)]
    truth = SE2.exp(jnp.asarray(xi))
    points = np.random.default_rng(1).normal(size=(LANDMARKS, 2)) * 3.0
    i = np.arange(n - 1)
    odometry = truth[i].between(truth[i + 1]).rplus(jnp.asarray(0.02 * rng.normal(size=(n - 1, 3))))
    roots = np.diag([10.0, 10.0, 20.0]) * rng.uniform(0.5, 1.5, size=(n - 1, 1, 1))
    seen = np.arange(n) % LANDMARKS
    observed = truth.inverse() @ jnp.asarray(points[seen]) + 0.05 * rng.normal(size=(n, 2))
    start = truth.rplus(jnp.asarray(0.1 * rng.normal(size=(n, 3))))
    poses = Var(start, fixed=[n // 2], name="poses")
    landmarks = Var(jnp.asarray(points + 0.2), name="landmarks")
    factors = [
        Factor(between_error, (poses[i], poses[i + 1]), odometry, sqrt_information=roots,
               loss=Huber(0.5), name="odo"),
        Factor(prior_error, (poses[np.array([0])],), truth[:1], sigmas=[0.01] * 3, name="prior"),
        Factor(sighting, (poses[np.arange(n)], landmarks[seen]), observed, sigmas=[0.2, 0.2],
               loss=Cauchy(1.0)),
    ]  # fmt: skip
    return FactorGraph(factors, [poses, landmarks], buckets=buckets)


@pytest.fixture(scope="module")
def references():
    """The unbucketed dense solve of each size (one compilation per size)."""
    return {n: window(n, False).solve(linear_solver="dense") for n in SIZES}


def assert_same(result, reference, tolerance):
    for value, expected in zip(result.values, reference.values):
        for a, b in zip(jax.tree.leaves(value), jax.tree.leaves(expected)):
            assert a.shape == b.shape
            np.testing.assert_allclose(a, b, rtol=0, atol=tolerance)
    np.testing.assert_allclose(result.cost, reference.cost, rtol=tolerance)
    assert int(result.iterations) == int(reference.iterations)


def test_bucket_size_rule():
    """Two buckets per doubling, at most a third padded, sizes up to 4 their own."""
    assert [bucket_size(n) for n in (0, 1, 4, 5, 7, 9, 12, 13, 50, 65, 97, 129)] == [
        1, 1, 4, 6, 8, 12, 12, 16, 64, 96, 128, 192,
    ]  # fmt: skip
    for n in range(1, 300):
        size = bucket_size(n)
        assert size >= n and (size - n) <= max(size // 3, 0)


@pytest.mark.parametrize("solver", ["dense", "cg", "cholesky"])
def test_growing_window_compiles_once_per_bucket(solver, references):
    """Sizes 10, 11, 12 (one bucket) compile the loop once and nothing else (no XLA compilation
    after the first solve); 13 (the poses' next bucket) compiles it once more. Each solve equals
    the unbucketed one (CG: inexact steps, to 1e-8)."""
    events = _COMPILED
    tolerance = 1e-8 if solver == "cg" else 1e-10
    graphs = {n: window(n, True) for n in SIZES}
    assert len({graphs[n]._buckets.key for n in SIZES[:3]}) == 1
    before = set(_graph._BUCKET_LOOPS)
    counts = []
    for n in SIZES:
        start = len(events)
        result = graphs[n].solve(linear_solver=solver)
        counts.append(len(events) - start)
        assert_same(result, references[n], tolerance)
    loops = [_graph._BUCKET_LOOPS[k] for k in set(_graph._BUCKET_LOOPS) - before]
    assert len(loops) == 2 and all(loop._cache_size() == 1 for loop in loops)
    assert counts[0] >= 1 and counts[1:3] == [0, 0] and counts[3] >= 1, counts
    again = window(11, True, seed=5)  # new measurements and start, same buckets
    start = len(events)
    again.solve(linear_solver=solver)
    assert len(events) == start


def test_auto_and_bad_options(monkeypatch):
    """`"auto"` picks by the bucketed size (the multifrontal Cholesky at every size where the
    native library runs it); an explicit elimination is refused, naming why."""
    graph = window(10, True)
    expected = "cholesky" if _multifrontal.native() else "dense"
    assert graph._loop(_graph.GTSAM, "auto", "auto", 100, None, False, None)[2] == expected
    monkeypatch.setattr(_multifrontal, "native", lambda: False)
    assert graph._loop(_graph.GTSAM, "auto", "auto", 100, None, False, None)[2] == "dense"
    with pytest.raises(ValueError, match="buckets=True.*eliminate="):
        graph.solve(eliminate=graph.variables[1])


def test_marginals_of_a_bucketed_graph(references):
    """Marginals of a bucketed graph (its own linearization: the loop holds the buckets'
    system) equal the unbucketed graph's at the same values."""
    n = SIZES[0]
    bucketed, plain = window(n, True), window(n, False)
    values = references[n].values
    for k in range(2):
        np.testing.assert_allclose(
            marginal_covariances(bucketed, values, bucketed.variables[k]),
            marginal_covariances(plain, values, plain.variables[k]),
            rtol=1e-10, atol=1e-14,
        )  # fmt: skip


def test_vmap_over_measurements():
    """Under `vmap` over measurements each problem equals its own solve, for two sizes of one
    bucket (the padding traced, the loop called on batched operands)."""
    for n in SIZES[:2]:
        graph = window(n, True)
        prior_data = graph.data[1][0]
        shifts = jnp.asarray([[0.0, 0.0, 0.0], [0.1, -0.2, 0.05]])

        def solved(shift, graph=graph, prior_data=prior_data):
            moved = prior_data.rplus(shift[None])
            result = graph.solve(
                data=[None, (moved, graph.data[1][1], None), None], linear_solver="dense"
            )
            return result.values[0].parameters(), result.cost

        values, costs = jax.vmap(solved)(shifts)
        for k in range(2):
            one, cost = solved(shifts[k])
            np.testing.assert_allclose(values[k], one, atol=1e-10)
            np.testing.assert_allclose(costs[k], cost, rtol=1e-10)


@pytest.mark.slow
def test_implicit_derivatives():
    """The implicit derivative of the first pose with respect to its prior equals the unbucketed
    graph's (13 s of compilation: each graph's dense-Hessian tangent program)."""
    graph, plain = window(SIZES[1], True), window(SIZES[1], False)
    direction = jnp.asarray([0.3, -0.2, 0.1])

    def moved(graph):
        def first_pose(shift):
            data = graph.data[1][0].rplus(shift[None])
            result = graph.solve(
                data=[None, (data, graph.data[1][1], None), None], linear_solver="dense"
            )
            return result.values[0].parameters()[0]

        return jax.jvp(first_pose, (jnp.zeros(3),), (direction,))[1]

    derivative = moved(graph)
    assert float(jnp.linalg.norm(derivative)) > 0.1  # the first pose follows its tight prior
    np.testing.assert_allclose(derivative, moved(plain), atol=1e-9)
