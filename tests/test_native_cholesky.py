"""The multifrontal Cholesky's numeric phase in C++ (`lieax.factorgraph._native_cholesky`,
`csrc/cholesky.cc`): the same solutions as the NumPy plan and the dense matrix on chains, trees,
grids, one block and random patterns of block sizes 1, 3 and 6; NaN when not positive definite;
`vmap` and float32; the registry's keys (unknown, collected, analysed in the background, failed);
the keyed solve (the plan named by an operand, padded pair blocks) of bucketed factor graphs;
and a second process that loads `graph.optimize`'s and `FactorGraph.solve`'s programs from the
persistent compilation cache without compiling any."""

import dataclasses
import gc
import textwrap
import threading
import time

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from _child import child_output
from test_sparse_multifrontal import system_on_edges

from lieax.factorgraph import _block_pattern, _multifrontal, _native_cholesky

pytestmark = pytest.mark.skipif(
    not _native_cholesky.available(), reason="the native library is not built (see setup.py)"
)


def edges_of(kind, n, rng):
    if kind == "chain":
        return np.arange(n - 1), np.arange(1, n)
    if kind == "tree":  # each block joined to a random earlier one
        j = np.arange(1, n)
        return rng.integers(0, j), j
    if kind == "grid":  # a 2D grid, rows of 5
        index = np.arange(n).reshape(-1, 5)
        right = index[:, :-1].ravel(), index[:, 1:].ravel()
        down = index[:-1].ravel(), index[1:].ravel()
        return np.concatenate([right[0], down[0]]), np.concatenate([right[1], down[1]])
    i = np.concatenate([np.arange(n - 1), rng.integers(0, n, n)])  # random: chain and chords
    j = np.concatenate([np.arange(1, n), rng.integers(0, n, n)])
    keep = i != j
    return i[keep], j[keep]


def system(kind, n, d, seed=0):
    """A pattern of `kind`, a diagonally dominant (positive definite) system on it, its dense
    matrix and a right-hand side."""
    rng = np.random.default_rng(seed)
    i, j = edges_of(kind, n, rng) if n > 1 else (np.zeros(0, int), np.zeros(0, int))
    return system_on_edges(n, d, i, j, rng)


CASES = [
    ("chain", 30, 6), ("tree", 40, 3), ("grid", 60, 3), ("random", 80, 6), ("random", 50, 1),
    ("single", 1, 3), ("grid", 30, 1),
]  # fmt: skip


@pytest.mark.parametrize(("kind", "n", "d"), CASES)
def test_native_solve_matches_numpy_plan_and_dense(kind, n, d):
    pattern, diag, off, dense, rhs = system(kind, n, d)
    plan = _multifrontal.CholeskyPlan.analyze(pattern)
    x = np.asarray(_native_cholesky.solve(plan.key, diag, off, rhs))
    expected = np.linalg.solve(dense, rhs.ravel()).reshape(n, d)
    np.testing.assert_allclose(x, expected, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(x, plan.solve(diag, off, rhs), rtol=1e-12, atol=1e-13)


def test_large_fronts_call_the_blas():
    """A grid whose separators make fronts above the plain loops' size (the BLAS path)."""
    pattern, diag, off, dense, rhs = system("grid", 200, 6, seed=3)
    plan = _multifrontal.CholeskyPlan.analyze(pattern)
    assert max(len(p) for p in plan_fronts(plan)) * 6 >= 24
    x = np.asarray(_native_cholesky.solve(plan.key, diag, off, rhs))
    np.testing.assert_allclose(x, np.linalg.solve(dense, rhs.ravel()).reshape(rhs.shape),
                               rtol=1e-11, atol=1e-12)  # fmt: skip


def plan_fronts(plan):
    """The pivot blocks of each batch's fronts (the NumPy plan's view of the fronts)."""
    return [row[row < plan.pattern.num_blocks] for b in plan.batches for row in b.pivot_index]


def test_not_positive_definite_is_nan():
    pattern, diag, off, _, rhs = system("random", 40, 3, seed=2)
    plan = _multifrontal.CholeskyPlan.analyze(pattern)
    for block in (plan.order[0], plan.order[-1]):  # a leaf front's pivot, the root's
        bad = diag.copy()
        bad[block] *= -1.0
        assert np.all(np.isnan(np.asarray(_native_cholesky.solve(plan.key, bad, off, rhs))))


def test_vmap_is_one_call_for_the_batch_and_float32():
    pattern, diag, off, dense, rhs = system("random", 30, 3, seed=5)
    plan = _multifrontal.CholeskyPlan.analyze(pattern)
    scales = np.array([1.0, 2.0, 3.5])
    diags = diag[None] * scales[:, None, None, None]
    run = jax.vmap(lambda a, r: _multifrontal.cholesky_solve(plan, a, jnp.asarray(off), r))
    x = jax.jit(run)(diags, np.stack([rhs] * 3))
    for s, xs in zip(scales, np.asarray(x)):
        matrix = np.asarray(_block_pattern.dense_matrix(pattern, jnp.asarray(s * diag), off))
        np.testing.assert_allclose(xs, np.linalg.solve(matrix, rhs.ravel()).reshape(rhs.shape),
                                   rtol=1e-12, atol=1e-12)  # fmt: skip
    hlo = jax.jit(run).lower(diags, np.stack([rhs] * 3)).as_text()
    assert hlo.count(_native_cholesky.TARGET) == 1
    single = [a.astype(np.float32) for a in (diag, off, rhs)]
    x32 = _native_cholesky.solve(plan.key, *single)
    assert x32.dtype == jnp.float32
    expected = np.linalg.solve(dense, rhs.ravel()).reshape(rhs.shape)
    np.testing.assert_allclose(x32, expected, rtol=2e-4, atol=2e-5)


def test_auto_factors_a_few_poses_by_the_multifrontal(monkeypatch):
    """`linear_solver="auto"` factors even a graph of nine poses (tinyGrid3D's size) by the
    native multifrontal Cholesky, which is faster than the dense matrix at every size measured
    (`lieax.factorgraph._graph._DENSE_LIMIT`); without the native library it factors the dense
    matrix. Both reach the same iterates."""
    from test_graph import noisy_graph

    from lieax import SE3
    from lieax import graph as lg
    from lieax.factorgraph import _graph

    graph, _ = noisy_graph(SE3, n=9, loops=2, seed=1)
    factor_graph = lg.to_factor_graph(graph)[0]
    assert _graph._auto_method(factor_graph.layout) == "cholesky"
    multifrontal = factor_graph.solve(linear_solver="auto")
    monkeypatch.setattr(_multifrontal, "native", lambda: False)
    assert _graph._auto_method(factor_graph.layout) == "dense"
    dense = factor_graph.solve(linear_solver="auto")
    assert {"dense", "cholesky"} <= {key[2] for key in factor_graph._loops}
    assert int(dense.iterations) == int(multifrontal.iterations)
    np.testing.assert_allclose(dense.cost_history, multifrontal.cost_history, rtol=1e-10)


def test_unknown_and_collected_keys_are_clear_errors():
    pattern, diag, off, _, rhs = system("chain", 10, 3, seed=7)
    with pytest.raises(Exception, match="no plan is registered under key 12345"):
        np.asarray(_native_cholesky.solve(12345, diag, off, rhs))
    plan = _multifrontal.CholeskyPlan.analyze(pattern, max_pivots=(1, 1, 1))  # a key of its own
    key = plan.key
    second = _multifrontal.CholeskyPlan.analyze(pattern, max_pivots=(1, 1, 1))
    assert second.key == key and _native_cholesky.references(key) == 2
    del plan
    gc.collect()
    assert _native_cholesky.references(key) == 1
    np.asarray(_native_cholesky.solve(key, diag, off, rhs))  # the other plan still serves it
    del second
    gc.collect()
    assert _native_cholesky.references(key) == 0
    with pytest.raises(Exception, match=f"no plan is registered under key {key}"):
        np.asarray(_native_cholesky.solve(key, diag, off, rhs))


def test_an_inconsistent_analysis_is_refused():
    """The library checks what it is handed (rows in range and in elimination order, every entry
    and child update inside its front) before it registers anything."""
    pattern, *_ = system("grid", 30, 3, seed=11)
    plan = _multifrontal.CholeskyPlan.analyze(pattern)
    symbolic = plan._symbolic
    front = next(k for k, p in enumerate(symbolic.pivots) if len(p) > 1)
    pivots = list(symbolic.pivots)
    pivots[front] = pivots[front][::-1]
    child = next(k for k, c in enumerate(symbolic.children) if c)
    children = [list(c) for c in symbolic.children]
    children[child] = []  # an orphan subtree: its updates go nowhere
    for bad in (
        dataclasses.replace(symbolic, pivots=pivots),
        dataclasses.replace(symbolic, children=children),
        dataclasses.replace(symbolic, order=symbolic.order[::-1].copy()),
    ):
        with pytest.raises(RuntimeError, match="refused the analysis"):
            _native_cholesky.register(plan, 77, bad, True)
    assert _native_cholesky.references(77) == 0


def test_a_plan_given_as_a_function_is_analysed_when_traced():
    """A plan given as a function (`Layout.plan`, analysed in the background): the traced solve
    waits for the analysis and names its key; an analysis that fails is the solve's error."""
    pattern, diag, off, dense, rhs = system("tree", 25, 6, seed=8)
    done = {}

    def slow_plan():
        if "plan" not in done:
            time.sleep(0.3)
            done["plan"] = _multifrontal.CholeskyPlan.analyze(pattern)
        return done["plan"]

    solve = jax.jit(
        lambda a, b, r: _multifrontal.cholesky_solve(slow_plan, a, b, r, pattern=pattern)
    )
    x = solve(diag, off, rhs)
    np.testing.assert_allclose(x, np.linalg.solve(dense, rhs.ravel()).reshape(rhs.shape),
                               rtol=1e-12, atol=1e-12)  # fmt: skip
    other, diag, off, _, rhs = system("grid", 20, 3, seed=9)

    def failing():
        raise ValueError("the analysis broke")

    solve = jax.jit(lambda a, b, r: _multifrontal.cholesky_solve(failing, a, b, r, pattern=other))
    with pytest.raises(ValueError, match="the analysis broke"):
        solve(diag, off, rhs)


def test_concurrent_solves_share_a_plan():
    pattern, diag, off, dense, rhs = system("random", 60, 6, seed=10)
    plan = _multifrontal.CholeskyPlan.analyze(pattern)
    solve = jax.jit(lambda a, b, r: _multifrontal.cholesky_solve(plan, a, b, r))
    expected = np.linalg.solve(dense, rhs.ravel()).reshape(rhs.shape)
    solve(diag, off, rhs).block_until_ready()
    results = [None] * 4

    def worker(k):
        results[k] = np.asarray(solve(diag, off, (k + 1.0) * rhs))

    threads = [threading.Thread(target=worker, args=(k,)) for k in range(4)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    for k, x in enumerate(results):
        np.testing.assert_allclose(x, (k + 1.0) * expected, rtol=1e-12, atol=1e-12)


CHILD = textwrap.dedent(
    """
    import sys, jax
    jax.config.update("jax_enable_x64", True)
    import numpy as np, lieax
    from lieax import SE2
    from lieax import graph as lg
    from lieax.factorgraph import Factor, FactorGraph, Var, _graph
    lieax.enable_compilation_cache(sys.argv[1])
    _graph._DENSE_LIMIT = 0  # the multifrontal Cholesky even for this small graph
    events = []  # a program read from the cache also reports a backend compilation
    jax.monitoring.register_event_listener(lambda event, **kw: events.append(event))
    jax.monitoring.register_event_duration_secs_listener(
        lambda event, duration, **kw: events.append(event)
    )
    rng = np.random.default_rng(0)
    n = 12
    truth = SE2.exp(rng.normal(size=(n, 3)))
    i = np.concatenate([np.arange(n - 1), [0, 3]])
    j = np.concatenate([np.arange(1, n), [5, 9]])
    measured = truth[i].between(truth[j])
    graph = lg.PoseGraph.create(truth.rplus(0.1 * rng.normal(size=(n, 3))),
                                np.stack([i, j], 1), measured)
    result = lg.optimize(graph)
    assert result.converged, result
    poses = Var(truth.rplus(0.1 * rng.normal(size=(n, 3))), name="poses", fixed=[0])
    between = lambda a, b, z: z.between(a.between(b)).log()
    solved = FactorGraph([Factor(between, (poses[i], poses[j]), measured)]).solve(
        linear_solver="cholesky")
    assert solved.converged
    loaded = events.count("/jax/compilation_cache/cache_hits")
    print(events.count("/jax/core/compile/backend_compile_duration") - loaded, loaded)
    """
)


def test_second_process_compiles_nothing(tmp_path):
    run = lambda: child_output(CHILD, tmp_path).split()[-2:]
    compiled, loaded = run()
    assert int(compiled) > 0 and loaded == "0"  # first process: compiled and written
    # second process: every program read back, the solve loops (the pose graph's and the
    # factor graph's) from lieax's store, the others from JAX's cache
    stored = len(list((tmp_path / "lieax-programs").glob("*.bin")))
    assert stored == 2
    assert run() == ["0", str(int(compiled) - stored)]


@pytest.mark.parametrize("path", ["native", "host", "host, library built"])
def test_keyed_solve_serves_every_plan_of_its_shapes(path, monkeypatch):
    """`cholesky_solve_keyed` (a bucketed factor graph's solve): one compiled program solves
    systems of two patterns (a chain and a tree of 30 blocks) by the plan its key operand names,
    with the pair blocks padded to 40 (the padding not read); native custom call and host
    callback alike (the host's also where the library is built but JAX is not on the CPU: the
    key `keep_keyed` hands out is the one the path reads), and under `vmap`."""
    if path == "host":
        monkeypatch.setattr(_native_cholesky, "available", lambda: False)
    elif path == "host, library built":
        monkeypatch.setattr(_multifrontal, "native", lambda: False)
    solve = jax.jit(lambda *system: _multifrontal.cholesky_solve_keyed(*system))  # traced here
    for kind in ("chain", "tree"):
        pattern, diag, off, dense, rhs = system(kind, 30, 3, seed=4)
        plan = _multifrontal.CholeskyPlan.analyze(pattern)
        key = _native_cholesky.key_words(_multifrontal.keep_keyed(plan))
        padded = np.concatenate([off, np.full((40 - len(off), 3, 3), np.nan)])
        x = np.asarray(solve(key, diag, padded, rhs))
        expected = np.linalg.solve(dense, rhs.ravel()).reshape(rhs.shape)
        np.testing.assert_allclose(x, expected, rtol=1e-11, atol=1e-12)
        batch = jax.vmap(solve, in_axes=(None, None, None, 0))(
            key, diag, padded, np.stack([rhs, 2 * rhs])
        )
        np.testing.assert_allclose(batch[1], 2 * expected, rtol=1e-11, atol=1e-12)
    assert solve._cache_size() == 1
