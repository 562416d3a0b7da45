"""lieax's thread scopes (`lieax._threads`): the setting and its errors, the BLAS limit inside the
host Cholesky's callback and around the compiled call of XLA's dense Cholesky, pykdtree's OpenMP limit, and the
counts restored after every call."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import lieax
from lieax import SE2, _threads
from lieax.factorgraph import (
    Factor,
    FactorGraph,
    Var,
    _block_pattern,
    _dense_solve,
    _multifrontal,
    _native_cholesky,
)


def blas_counts():
    return [pool.get_num_threads() for pool in _threads._pools("blas")]


@pytest.fixture
def two_blas_threads():
    """Every BLAS pool at 2 threads where it can have them (the user's setting to restore)."""
    _threads.prepare()
    pools = _threads._pools("blas")
    saved = [pool.get_num_threads() for pool in pools]
    for pool in pools:
        pool.set_num_threads(2)
    yield blas_counts()
    for pool, count in zip(pools, saved):
        pool.set_num_threads(count)


@pytest.mark.parametrize("value", [0, -3])
def test_set_threads_rejects_nonpositive(value):
    with pytest.raises(ValueError, match=r"lieax\.set_threads\(n\) must be a positive integer"):
        lieax.set_threads(value)
    with pytest.raises(ValueError, match=r"lieax\.threads\(n\)"):
        with lieax.threads(value):
            pass


@pytest.mark.parametrize("value", [1.5, True, "2"])
def test_set_threads_rejects_non_integers(value):
    with pytest.raises(TypeError, match=r"lieax\.set_threads\(n\)"):
        lieax.set_threads(value)


@pytest.mark.parametrize("text", ["0", "-1", "two", "1.5"])
def test_environment_variable_is_checked(monkeypatch, text):
    monkeypatch.setenv("LIEAX_NUM_THREADS", text)
    with pytest.raises(ValueError, match="LIEAX_NUM_THREADS"):
        _threads._from_environment()


def test_environment_variable_values(monkeypatch):
    for text, expected in (("", None), ("auto", None), (" 3 ", 3)):
        monkeypatch.setenv("LIEAX_NUM_THREADS", text)
        assert _threads._from_environment() == expected


def test_unknown_blas_is_an_error_naming_the_setting(monkeypatch):
    monkeypatch.setattr(_threads, "_pools", lambda user_api: [])
    with pytest.raises(RuntimeError, match=r"lieax\.set_threads\(n\) cannot be honoured"):
        lieax.set_threads(2)
    lieax.set_threads(None)  # the libraries' own setting needs no BLAS


def test_threads_context_restores_the_setting():
    assert lieax.get_threads() is None
    with lieax.threads(3):
        assert lieax.get_threads() == 3
        with lieax.threads(1):
            assert lieax.get_threads() == 1
        assert lieax.get_threads() == 3
    assert lieax.get_threads() is None
    with pytest.raises(KeyError), lieax.threads(2):
        raise KeyError
    assert lieax.get_threads() is None


def test_threads_for_small_and_large_work():
    assert _threads.threads_for(10, 100) == 1
    assert _threads.threads_for(100, 100) is None
    with lieax.threads(2):
        assert _threads.threads_for(10, 100) == 1
        assert _threads.threads_for(1000, 100) == 2


def chain_system(n, d, seed=0):
    """A positive definite block tridiagonal system: pattern, diag, off, rhs (NumPy)."""
    rng = np.random.default_rng(seed)
    pattern, _, _ = _block_pattern.BlockPattern.from_edges(n, d, np.arange(n - 1), np.arange(1, n))
    off = 0.1 * rng.normal(size=(n - 1, d, d))
    a = rng.normal(size=(n, d, d))
    diag = a @ np.swapaxes(a, 1, 2) + 2 * d * np.eye(d)
    return pattern, diag, off, rng.normal(size=(n, d))


def test_host_cholesky_runs_on_one_blas_thread_and_restores(monkeypatch, two_blas_threads):
    """The NumPy path (without the native library: the host callback)."""
    monkeypatch.setattr(_native_cholesky, "available", lambda: False)
    pattern, diag, off, rhs = chain_system(40, 6)
    plan = _multifrontal.CholeskyPlan.analyze(pattern)
    seen = []
    solve = _multifrontal.CholeskyPlan.solve

    def recording(self, *system):
        seen.append(blas_counts())
        return solve(self, *system)

    monkeypatch.setattr(_multifrontal.CholeskyPlan, "solve", recording)
    run = jax.jit(lambda d, o, r: _multifrontal.cholesky_solve(plan, d, o, r))
    x = run(diag, off, rhs)
    dense = _block_pattern.dense_matrix(pattern, diag, off)
    np.testing.assert_allclose(x.reshape(-1), np.linalg.solve(dense, rhs.reshape(-1)), rtol=1e-10)
    assert seen and all(counts == [1] * len(counts) for counts in seen)
    assert blas_counts() == two_blas_threads
    # a plan above the threshold keeps the user's counts (None), or lieax's setting
    monkeypatch.setitem(plan.stats, "flops", 2 * _threads.PARALLEL_FLOPS)
    seen.clear()
    solve_again = jax.jit(lambda d, o, r: _multifrontal.cholesky_solve(plan, d, o, r))
    solve_again(diag, off, rhs).block_until_ready()
    assert seen == [two_blas_threads]


@pytest.mark.skipif(not _native_cholesky.available(), reason="the native library is not built")
def test_native_cholesky_scopes_its_blas_calls(two_blas_threads):
    """The native path sets OpenBLAS's thread-local count around its BLAS calls (found next to
    SciPy's BLAS) and leaves the pools' counts as they were."""
    assert _native_cholesky.scopes_threads()
    pattern, diag, off, rhs = chain_system(40, 6)
    plan = _multifrontal.CholeskyPlan.analyze(pattern)
    x = jax.jit(lambda d, o, r: _multifrontal.cholesky_solve(plan, d, o, r))(diag, off, rhs)
    dense = _block_pattern.dense_matrix(pattern, diag, off)
    np.testing.assert_allclose(x.reshape(-1), np.linalg.solve(dense, rhs.reshape(-1)), rtol=1e-10)
    assert blas_counts() == two_blas_threads


def dense_chain_graph(n):
    """A factor graph whose `linear_solver="dense"` system has order `3 n`: a chain of `n` SE2 poses
    with a prior on the first."""
    rng = np.random.default_rng(0)
    truth = SE2.exp(rng.normal(size=(n, 3)))
    poses = Var(truth.rplus(0.05 * rng.normal(size=(n, 3))), name="poses")
    i, j = np.arange(n - 1), np.arange(1, n)
    between = lambda a, b, z: z.between(a.between(b)).log()
    prior = lambda x, z: z.between(x).log()
    return FactorGraph(
        [
            Factor(between, (poses[i], poses[j]), truth[i].between(truth[j])),
            Factor(prior, (poses[np.array([0])],), truth[:1]),
        ]
    )


def test_dense_cholesky_runs_on_one_blas_thread_around_the_compiled_call(
    monkeypatch, two_blas_threads
):
    """Orders from 64 (`SINGLE_THREAD_ORDER`): the BLAS pools at 1 thread while the compiled
    solve runs (set around the call, so the program holds no host callback: JAX's persistent
    cache can keep it, and `vmap` of it works), the counts restored after; none below."""
    graph = dense_chain_graph(30)  # order 90
    assert _dense_solve.dense_threads(graph.layout.pattern) == 1
    seen = []
    enter = _threads._enter_blas

    def recording(threads, only_shared=False):
        enter(threads, only_shared)
        seen.append(blas_counts())

    monkeypatch.setattr(_threads, "_enter_blas", recording)
    result = graph.solve(linear_solver="dense")
    assert result.converged
    ones = [1] * len(two_blas_threads)
    assert seen == [ones]
    assert blas_counts() == two_blas_threads and _threads._BLAS_SCOPE["depth"] == 0
    # the same program batched: no callback in it, so vmap of its loop's cond works
    values = jax.tree_util.tree_map(lambda x: jnp.stack([x, x]), graph.initial_values)
    batched = jax.vmap(lambda v: graph.solve(v, linear_solver="dense", throw=False).cost)(values)
    np.testing.assert_allclose(batched, float(result.cost), rtol=1e-12)
    small = dense_chain_graph(4)  # order 12: OpenBLAS stays on the calling thread
    assert _dense_solve.dense_threads(small.layout.pattern) is None


def test_kdtree_queries_limit_openmp_by_size():
    pytest.importorskip("pykdtree")
    from lieax.icp import _host_kdtree

    _threads.prepare()
    if not _threads._pools("openmp"):
        pytest.skip("no OpenMP runtime loaded")
    openmp_counts = lambda: [pool.get_num_threads() for pool in _threads._pools("openmp")]
    before = openmp_counts()

    class Recording:
        seen = []

        def query(self, queries, k, **options):
            self.seen.append(openmp_counts())
            return np.zeros((len(queries), k)), np.zeros((len(queries), k), int)

    tree = Recording()
    _host_kdtree.tree_query(tree, np.zeros((10, 3)), 1)
    _host_kdtree.tree_query(tree, np.zeros((_threads.PARALLEL_NEIGHBOURS, 3)), 1)
    with lieax.threads(1):
        _host_kdtree.tree_query(tree, np.zeros((_threads.PARALLEL_NEIGHBOURS, 3)), 1)
    ones = [1] * len(before)
    assert tree.seen == [ones, before, ones]
    assert openmp_counts() == before
