"""Tests of lieax.graph: factors and their Jacobians, g2o files, the block Cholesky, Levenberg-
Marquardt against GTSAM's reference costs, initialisation, and bad input.

Real data comes from `$LIEAX_DATA_DIR/g2o` (tests needing it skip without it); everything else runs
on generated graphs. Each distinct graph structure compiles the optimizer once, so the tests reuse
a few structures.
"""

import os

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import lieax
from lieax import SE2, SE3, retractions
from lieax import graph as lg
from lieax.factorgraph import (
    _block_pattern,
    _dense_solve,
    _host_triangular,
    _multifrontal,
    _native_cholesky,
    _ordering,
    _pcg,
)
from lieax.factorgraph import _graph as factorgraph_module
from lieax.graph import _optimize
from lieax.lstsq import Termination

jax.config.update("jax_enable_x64", True)

DATA = os.environ.get("LIEAX_DATA_DIR")
G2O = None if DATA is None else os.path.join(DATA, "g2o")
needs_data = pytest.mark.skipif(
    G2O is None or not os.path.isdir(G2O), reason="LIEAX_DATA_DIR/g2o not available"
)

# GTSAM 4.3 LevenbergMarquardtOptimizer, default parameters, tight prior on the first pose
# (benchmarks/pgo.py): final error and outer iterations.
GTSAM_REFERENCE = {
    "tinyGrid3D.g2o": (9.313909533600565, 5),
    "smallGrid3D.g2o": (517.925334677437, 7),
    "intel.g2o": (22.502116544407084, 3),
}


# ---- generated graphs ----------------------------------------------------------------------------


def noisy_graph(group, n=30, loops=15, sigma=0.05, init_sigma=0.2, seed=0):
    """`n` poses along a curve with odometry edges and `loops` loop closures; measurements are
    the truth perturbed with `sigma`, initial poses the truth perturbed with `init_sigma` (the
    first pose exact)."""
    rng = np.random.default_rng(seed)
    d = group.tangent_dim
    xi = rng.normal(size=(n, d)) * 0.3
    xi[:, 0] += np.arange(n) * 1.0  # spread along the first axis
    truth = group.exp(jnp.asarray(xi))
    i = list(range(n - 1))
    j = list(range(1, n))
    while len(i) < n - 1 + loops:
        a, b = sorted(rng.choice(n, 2, replace=False).tolist())
        if b - a > 1:
            i.append(a)
            j.append(b)
    i, j = np.array(i), np.array(j)
    noise = jnp.asarray(rng.normal(size=(len(i), d)) * sigma)
    measured = truth[i].between(truth[j]).rplus(noise)
    information = np.diag(rng.uniform(0.5, 2.0, size=d)) / sigma**2
    initial = truth.rplus(jnp.asarray(rng.normal(size=(n, d)) * init_sigma).at[0].set(0.0))
    graph = lg.PoseGraph.create(initial, np.stack([i, j], 1), measured, information)
    return graph, truth


def relative_close(a, b, tol):
    return abs(a - b) <= tol * abs(b)


# ---- factors -------------------------------------------------------------------------------------


@pytest.mark.parametrize("group", [SE2, SE3])
def test_between_jacobians_match_autodiff(group):
    @jax.jit
    def blocks(X_i, X_j, Z):
        closed = lg.between_jacobians(X_i, X_j, Z)
        auto = lieax.jacobian(lambda a, b: lg.between_error(a, b, Z), argnums=(0, 1))(X_i, X_j)
        approximate = lg.between_jacobians(X_i, X_j, Z, exact=False)
        prior = lg.prior_jacobian(X_j, Z)
        prior_auto = lieax.jacobian(lambda x: lg.prior_error(x, Z))(X_j)
        return closed, auto, approximate, prior, prior_auto, X_i.between(X_j).inverse().adjoint()

    key = jax.random.PRNGKey(0)
    for trial in range(4):
        k1, k2, k3, key = jax.random.split(key, 4)
        X_i = group.sample_uniform(k1)
        X_j = group.sample_uniform(k2)
        Z = X_i.between(X_j).rplus(0.3 * jax.random.normal(k3, (group.tangent_dim,)))
        if trial == 3:  # an exact measurement: e = 0, Jr⁻¹ = I
            Z = X_i.between(X_j)
        (e, J_i, J_j), (auto_i, auto_j), (_, A_i, A_j), (_, J_p), auto_p, ad = blocks(X_i, X_j, Z)
        np.testing.assert_allclose(J_i, auto_i, atol=1e-9)
        np.testing.assert_allclose(J_j, auto_j, atol=1e-9)
        np.testing.assert_allclose(J_p, auto_p, atol=1e-9)
        # GTSAM's first-order blocks: -Ad((X_i⁻¹ X_j)⁻¹) and I
        np.testing.assert_allclose(A_i, -ad, atol=1e-12)
        np.testing.assert_allclose(A_j, np.eye(group.tangent_dim), atol=0)
        if trial == 3:
            np.testing.assert_allclose(e, 0.0, atol=1e-12)
            np.testing.assert_allclose(J_i, -ad, atol=1e-12)


def test_between_jacobians_batched():
    key = jax.random.PRNGKey(1)
    X = SE3.sample_uniform(key, (5,))
    Z = X[:-1].between(X[1:])
    e, J_i, J_j = jax.jit(lg.between_jacobians)(X[:-1], X[1:], Z)
    assert e.shape == (4, 6) and J_i.shape == (4, 6, 6) and J_j.shape == (4, 6, 6)
    np.testing.assert_allclose(e, 0.0, atol=1e-12)
    np.testing.assert_allclose(J_j, np.broadcast_to(np.eye(6), (4, 6, 6)), atol=1e-12)


# ---- g2o files -----------------------------------------------------------------------------------


@pytest.mark.parametrize("group", [SE2, SE3])
def test_g2o_round_trip(tmp_path, group):
    graph, _ = noisy_graph(group, n=8, loops=3)
    graph = graph.replace(vertex_ids=np.arange(8) * 10 + 5).with_fixed([2])
    path = tmp_path / "graph.g2o"
    lg.write_g2o(path, graph)
    back = lg.read_g2o(path)
    assert back.group is group
    np.testing.assert_array_equal(back.vertex_ids, graph.vertex_ids)
    np.testing.assert_array_equal(back.edges, graph.edges)
    np.testing.assert_array_equal(back.fixed, [2])
    np.testing.assert_allclose(back.information, graph.information, rtol=1e-12)
    np.testing.assert_allclose(back.poses.rminus(graph.poses), 0.0, atol=1e-12)
    np.testing.assert_allclose(back.measurements.rminus(graph.measurements), 0.0, atol=1e-12)
    assert relative_close(float(lg.cost(back)), float(lg.cost(graph)), 1e-12)


def test_g2o_se3_information_is_translation_first(tmp_path):
    """g2o orders SE3 information (t, R) like lieax's tangent: diag(1..6) stays diag(1..6), and
    the cost weighs translation errors with the first block."""
    upper = []
    info = np.diag([1.0, 2.0, 3.0, 4.0, 5.0, 6.0])
    info[0, 4] = info[4, 0] = 0.5
    for r in range(6):
        upper += info[r, r:].tolist()
    path = tmp_path / "one.g2o"
    path.write_text(
        "VERTEX_SE3:QUAT 0 0 0 0 0 0 0 1\n"
        "VERTEX_SE3:QUAT 1 1 0 0 0 0 0 1\n"
        "EDGE_SE3:QUAT 0 1 0.9 0.1 0 0 0 0.0499792 0.99875 " + " ".join(map(str, upper)) + "\n"
    )
    graph = lg.read_g2o(path)
    np.testing.assert_allclose(graph.information[0], info, rtol=1e-12)
    e = lg.between_error(graph.poses[0], graph.poses[1], graph.measurements[0])
    assert abs(e[0] - 0.1) < 0.02 and abs(e[5] + 0.1) < 1e-3  # (v..., ω...) order
    np.testing.assert_allclose(float(lg.cost(graph)), 0.5 * float(e @ info @ e), rtol=1e-12)


BAD_FILES = {
    "malformed": (
        "VERTEX_SE2 0 0 0 0\nVERTEX_SE2 1 1 0 0\nEDGE_SE2 0 1 1 0 0 1 0 0 1 0\n",
        ":3",
        "fields",
    ),
    "not a number": ("VERTEX_SE2 0 0 0 0\nVERTEX_SE2 1 1 zero 0\n", ":2", "expected a number"),
    "bad FIX": ("VERTEX_SE2 0 0 0 0\n# comment\nFIX 1\n", ":3", "vertex 1"),
    "huge id": ("VERTEX_SE2 0 0 0 0\nVERTEX_SE2 99999999999999999999 0 0 0\n", ":2", "int64"),
    "missing vertex": ("VERTEX_SE2 0 0 0 0\nEDGE_SE2 0 7 1 0 0 1 0 0 1 0 1\n", ":2", "vertex 7"),
    "not positive definite": (
        "VERTEX_SE2 0 0 0 0\nVERTEX_SE2 1 1 0 0\n\nEDGE_SE2 0 1 1 0 0 -1 0 0 -1 0 -1\n",
        ":4",
        "no positive eigenvalue",
    ),
    "mixed dimensions": ("VERTEX_SE2 0 0 0 0\nVERTEX_SE3:QUAT 1 0 0 0 0 0 0 1\n", ":2", "mixed"),
    "duplicate vertex": ("VERTEX_SE2 0 0 0 0\nVERTEX_SE2 0 1 0 0\n", ":2", "already defined"),
    "self loop": ("VERTEX_SE2 0 0 0 0\nEDGE_SE2 0 0 1 0 0 1 0 0 1 0 1\n", ":2", "itself"),
    "zero quaternion": ("VERTEX_SE3:QUAT 0 0 0 0 0 0 0 0\n", ":1", "no rotation"),
    "empty": ("# nothing\n", "", "no pose-graph vertices"),
}


@pytest.mark.parametrize("case", sorted(BAD_FILES))
def test_g2o_bad_input(tmp_path, case):
    text, where, message = BAD_FILES[case]
    path = tmp_path / "bad.g2o"
    path.write_text(text)
    with pytest.raises(lg.G2oError, match=message) as info:
        lg.read_g2o(path)
    assert f"{path}{where}" in str(info.value)


def test_edges_only_file_composes_a_spanning_tree(tmp_path):
    graph, truth = noisy_graph(SE2, n=10, loops=0, sigma=1e-9)
    graph = graph.replace(vertex_ids=np.arange(10) + 100)
    path = tmp_path / "edges.g2o"
    lg.write_g2o(path, graph)
    text = "".join(line + "\n" for line in path.read_text().splitlines() if line.startswith("EDGE"))
    path.write_text(text)
    back = lg.read_g2o(path)
    np.testing.assert_array_equal(back.vertex_ids, np.arange(10) + 100)
    # the first pose is the identity (the tree's root), the others composed odometry
    np.testing.assert_allclose(back.poses.rminus(truth[0].inverse() @ truth), 0.0, atol=1e-6)
    # disconnected edges without vertices cannot be composed
    path.write_text("EDGE_SE2 0 1 1 0 0 1 0 0 1 0 1\nEDGE_SE2 2 3 1 0 0 1 0 0 1 0 1\n")
    with pytest.raises(lg.G2oError, match="disconnected"):
        lg.read_g2o(path)


# ---- sparse normal equations ---------------------------------------------------------------------


@pytest.mark.parametrize("n, extra, d", [(1, 0, 3), (2, 0, 6), (40, 30, 3), (120, 90, 6)])
def test_block_cholesky_matches_dense(n, extra, d):
    rng = np.random.default_rng(n)
    i = np.concatenate([np.arange(n - 1), rng.integers(0, n, extra)])
    j = np.concatenate([np.arange(1, n), rng.integers(0, n, extra)])
    keep = i != j
    pattern, _, _ = _block_pattern.BlockPattern.from_edges(n, d, i[keep], j[keep])
    off = rng.normal(size=(pattern.num_pairs, d, d))
    weight = np.abs(off).sum(axis=(1, 2))
    diag = np.zeros((n, d, d))
    np.add.at(diag, pattern.rows, weight[:, None, None] * np.eye(d))
    np.add.at(diag, pattern.cols, weight[:, None, None] * np.eye(d))
    M = rng.normal(size=(n, d, d))
    diag += M @ np.swapaxes(M, 1, 2) + np.eye(d)
    rhs = rng.normal(size=(n, d))
    dense = np.asarray(_block_pattern.dense_matrix(pattern, jnp.asarray(diag), jnp.asarray(off)))
    expected = np.linalg.solve(dense, rhs.ravel()).reshape(n, d)
    plan = _multifrontal.CholeskyPlan.analyze(pattern)
    np.testing.assert_allclose(plan.solve(diag, off, rhs), expected, rtol=1e-9, atol=1e-12)
    x, _ = _pcg.pcg(pattern, jnp.asarray(diag), jnp.asarray(off), jnp.asarray(rhs), tolerance=1e-12)
    np.testing.assert_allclose(x, expected, rtol=1e-7, atol=1e-9)
    # not positive definite: NaN, not an exception (the optimizer then raises the damping)
    assert np.all(np.isnan(plan.solve(-diag, off, rhs)))
    # from traced code (the native custom call, or the host call without it), also under vmap
    args = jnp.asarray(diag), jnp.asarray(off)
    traced = jax.jit(lambda r: _multifrontal.cholesky_solve(plan, *args, r))(jnp.asarray(rhs))
    np.testing.assert_allclose(traced, expected, rtol=1e-9, atol=1e-12)
    stacked = jnp.stack([jnp.asarray(rhs), 2.0 * jnp.asarray(rhs)])
    batched = jax.jit(jax.vmap(lambda r: _multifrontal.cholesky_solve(plan, *args, r)))(stacked)
    np.testing.assert_allclose(batched[1], 2.0 * expected, rtol=1e-9, atol=1e-12)
    if n * d <= 300:
        dense_x = _dense_solve.dense_solve(pattern, *args, jnp.asarray(rhs))
        np.testing.assert_allclose(dense_x, expected, rtol=1e-9, atol=1e-12)


@pytest.mark.parametrize("order", [5, 30, 63, 64, 150])
def test_triangular_inverse(order):
    """The host's triangular inverse, below and above the order (64) where it switches from
    LAPACK's unblocked routine to the blocked recursion."""
    rng = np.random.default_rng(order)
    a = rng.normal(size=(2, order, order))
    lower = np.linalg.cholesky(a @ np.swapaxes(a, 1, 2) + order * np.eye(order))
    np.testing.assert_allclose(
        _host_triangular._lower_inverse(lower) @ lower, np.broadcast_to(np.eye(order), lower.shape),
        atol=1e-12,
    )  # fmt: skip


def test_block_cholesky_of_a_forest():
    """Two components: two roots in one batch, each solved by its own factor."""
    d, rng = 6, np.random.default_rng(7)
    i, j = np.array([0, 1, 3, 4, 5]), np.array([1, 2, 4, 5, 6])
    pattern, _, _ = _block_pattern.BlockPattern.from_edges(7, d, i, j)
    off = 0.1 * rng.normal(size=(pattern.num_pairs, d, d))
    diag = np.broadcast_to(4.0 * np.eye(d), (7, d, d)).copy()
    rhs = rng.normal(size=(7, d))
    dense = np.asarray(_block_pattern.dense_matrix(pattern, jnp.asarray(diag), jnp.asarray(off)))
    plan = _multifrontal.CholeskyPlan.analyze(pattern)
    assert any(batch.shape[0] == 2 and batch.shape[2] == 0 for batch in plan.batches)
    np.testing.assert_allclose(
        plan.solve(diag, off, rhs), np.linalg.solve(dense, rhs.ravel()).reshape(7, d), rtol=1e-10
    )


def test_block_cholesky_keeps_one_work_array_per_thread(monkeypatch):
    """The NumPy path's host solves of `optimize`'s loop run on XLA's threads, whose Python thread state
    (and a `threading.local`'s data) is dropped after each call: they must reuse their thread's
    work array, not allocate one per solve (a `threading.local` allocated 9 in these 3 calls). Python threads sharing a plan each get their own and the right answer."""
    import threading

    graph, _ = noisy_graph(SE3, n=30, loops=40, sigma=0.02, init_sigma=0.05, seed=4)
    monkeypatch.setattr(factorgraph_module, "_DENSE_LIMIT", 0)
    # the NumPy path (as without the native library), in a loop traced for it
    monkeypatch.setattr(_native_cholesky, "available", lambda: False)
    monkeypatch.setattr(_optimize, "_CACHE", {})
    first = lg.optimize(graph)
    plan = _optimize._factor_graph(graph, exact=True).layout.plan()
    work_shape = (plan.work_rows, plan.pattern.block_size)
    allocated = []
    original = np.empty

    def counting_empty(*args, **kwargs):
        if args[0] == work_shape:
            allocated.append(threading.get_ident())
        return original(*args, **kwargs)

    with monkeypatch.context() as patch:
        patch.setattr(np, "empty", counting_empty)
        again = [lg.optimize(graph) for _ in range(3)]
    # at most one work array per thread (a thread first used here allocates one), not one
    # per solve
    assert first.linear_solves >= 2
    assert len(allocated) == len(set(allocated)) <= 2
    assert all(r.cost == first.cost for r in again)
    assert 1 <= len(plan._buffers) <= _multifrontal._MAX_BUFFERS
    # Python threads sharing the plan (more threads than buffers kept)
    rng = np.random.default_rng(3)
    n, d = plan.pattern.num_blocks, plan.pattern.block_size
    off = 0.1 * rng.normal(size=(plan.pattern.num_pairs, d, d))
    diag = np.broadcast_to(4.0 * np.eye(d), (n, d, d)).copy()
    rhs = rng.normal(size=(n, d))
    dense = np.asarray(
        _block_pattern.dense_matrix(plan.pattern, jnp.asarray(diag), jnp.asarray(off))
    )
    expected = np.linalg.solve(dense, rhs.ravel()).reshape(n, d)
    results = [None] * 6

    def worker(k):
        results[k] = plan.solve(diag, off, (k + 1.0) * rhs)

    threads = [threading.Thread(target=worker, args=(k,)) for k in range(6)]
    for t in threads:
        t.start()
    for t in threads:
        t.join()
    for k, x in enumerate(results):
        np.testing.assert_allclose(x, (k + 1.0) * expected, rtol=1e-10)
    assert len(plan._buffers) <= _multifrontal._MAX_BUFFERS


def test_nested_dissection_of_chains():
    """Two chains of 3-block rungs (an IMU smoother's shape: pose, velocity, bias per keyframe):
    minimum degree's elimination tree is tall (nearly a path), so `analyze` takes nested
    dissection, whose tree is logarithmically shallow, and both solutions are the dense one."""
    d, rungs, rng = 3, 150, np.random.default_rng(11)
    n = 2 * 3 * rungs  # two components
    base = 3 * np.arange(rungs - 1)
    one = np.concatenate([base, base + 1, base + 2, base, base + 1])
    other = np.concatenate([base + 3, base + 4, base + 5, base + 1, base + 2])
    rung = 3 * np.arange(rungs)
    one = np.concatenate([one, rung, rung])
    other = np.concatenate([other, rung + 1, rung + 2])
    i, j = np.concatenate([one, one + n // 2]), np.concatenate([other, other + n // 2])
    pattern, _, _ = _block_pattern.BlockPattern.from_edges(n, d, i, j)
    order = _ordering.nested_dissection_order(n, pattern.rows, pattern.cols)
    np.testing.assert_array_equal(np.sort(order), np.arange(n))
    by_degree = _multifrontal.CholeskyPlan.analyze(pattern, order=_ordering.minimum_degree_order(
        n, pattern.rows, pattern.cols
    ))  # fmt: skip
    plan = _multifrontal.CholeskyPlan.analyze(pattern)
    assert plan.stats["ordering"] == "nested dissection"
    assert plan.stats["height"] <= 2 * np.log2(rungs)
    assert 3 * plan.stats["height"] <= by_degree.stats["height"]
    off = 0.2 * rng.normal(size=(pattern.num_pairs, d, d))
    diag = np.broadcast_to(6.0 * np.eye(d), (n, d, d)).copy()
    rhs = rng.normal(size=(n, d))
    dense = np.asarray(_block_pattern.dense_matrix(pattern, jnp.asarray(diag), jnp.asarray(off)))
    expected = np.linalg.solve(dense, rhs.ravel()).reshape(n, d)
    np.testing.assert_allclose(plan.solve(diag, off, rhs), expected, rtol=1e-10, atol=1e-12)
    np.testing.assert_allclose(by_degree.solve(diag, off, rhs), expected, rtol=1e-10, atol=1e-12)


# ---- optimization --------------------------------------------------------------------------------


def gradient_norm(graph, poses):
    factor_graph = _optimize._factor_graph(graph, exact=True)
    _, _, _, (grad,) = factor_graph.linearize((poses,), _optimize.factor_data(graph))
    return float(jnp.max(jnp.abs(grad)))


def test_optimize_generated_2d_cholesky_and_cg_agree():
    graph, truth = noisy_graph(SE2, n=40, loops=20, seed=3)
    initial_cost = float(lg.cost(graph))
    tight = {
        "termination": Termination.gtsam(
            function_tolerance=1e-12, absolute_function_tolerance=1e-12
        )
    }
    result = lg.optimize(graph, **tight)
    assert result.status == lieax.Status.CONVERGED
    assert result.cost < 1e-2 * initial_cost
    assert result.cost_history[0] == pytest.approx(initial_cost)
    assert np.all(np.diff(result.cost_history) <= 0)
    assert len(result.cost_history) == result.iterations + 1
    assert relative_close(result.cost, float(lg.cost(graph, result.poses)), 1e-12)
    np.testing.assert_allclose(result.poses[0].parameters(), graph.poses[0].parameters(), atol=0)
    assert gradient_norm(graph, result.poses) < 1e-7 * gradient_norm(graph, graph.poses)
    cg = lg.optimize(graph, linear_solver="cg", cg_tolerance=1e-12, **tight)
    assert relative_close(cg.cost, result.cost, 1e-9)
    # the same structure with other values reuses the compiled loop
    count = len(_optimize._CACHE)
    again = lg.optimize(graph.with_poses(truth), termination=Termination.gtsam(max_iterations=3))
    assert len(_optimize._CACHE) == count and again.iterations <= 3


def test_optimize_refuses_transformations():
    """`optimize` returns concrete values: under `jit` it says so and names the traceable
    solve, before any work."""
    graph, _ = noisy_graph(SE2, n=6, loops=2, seed=4)
    with pytest.raises(TypeError, match="cannot run under jit.*FactorGraph.solve"):
        jax.jit(lambda: lg.optimize(graph).cost)()


def test_optimize_generated_3d_with_prior_and_robust_loss():
    from lieax.lstsq import Huber

    graph, truth = noisy_graph(SE3, n=30, loops=40, sigma=0.02, init_sigma=0.05, seed=4)
    # one gross outlier loop closure (100 sigmas)
    bad = graph.between.measured.parameters().at[-1, 4:].add(2.0)
    outlier = graph.replace(
        between=graph.between.__class__(
            graph.between.i, graph.between.j, SE3(bad), graph.between.sqrt_information
        )
    )
    anchored = outlier.with_prior(0, truth[0], np.eye(6) * 1e6).with_loss(Huber(3.0))
    result = lg.optimize(
        anchored,
        termination=Termination.gtsam(function_tolerance=1e-10, absolute_function_tolerance=1e-10),
    )
    assert result.status == lieax.Status.CONVERGED
    # the prior replaces the gauge: pose 0 may move, but stays at the prior
    np.testing.assert_allclose(result.poses[0].rminus(truth[0]), 0.0, atol=1e-3)
    # the robust loss leaves the outlier unexplained instead of bending the graph to it
    between = anchored.between
    e = lg.between_error(result.poses[between.i], result.poses[between.j], between.measured)
    norms = np.linalg.norm(np.einsum("kab,kb->ka", between.sqrt_information, e), axis=1)
    assert norms[-1] > 10 * np.percentile(norms[:-1], 90)
    assert np.abs(np.asarray(result.poses.rminus(truth))).max() < 0.5
    assert gradient_norm(anchored, result.poses) < 1e-5 * gradient_norm(anchored, anchored.poses)
    # robust cost: the outlier contributes ρ(s) < s
    plain = float(lg.cost(anchored.with_loss(None), result.poses))
    assert result.cost < plain


def test_retractions_reach_the_same_optimum():
    # Cayley and first-order steps take other paths to the same stationary point
    graph, _ = noisy_graph(SE3, n=30, loops=40, sigma=0.02, init_sigma=0.05, seed=4)
    tight = {
        "termination": Termination.gtsam(
            function_tolerance=1e-12, absolute_function_tolerance=1e-12
        )
    }
    reference = lg.optimize(graph, **tight)
    for retraction in (retractions.cayley, retractions.first_order):
        result = lg.optimize(graph, retraction=retraction, **tight)
        assert result.status == lieax.Status.CONVERGED
        assert relative_close(result.cost, reference.cost, 1e-9)
        assert np.abs(np.asarray(result.poses.rminus(reference.poses))).max() < 1e-6
        assert not np.allclose(result.cost_history[1], reference.cost_history[1], rtol=1e-12)
    with pytest.raises(TypeError, match="retraction"):
        lg.optimize(graph, retraction="cayley")


def test_dense_and_multifrontal_steps_agree(monkeypatch):
    # the dense matrix in JAX (what `optimize` picks for small graphs where the multifrontal
    # Cholesky has no native library) and the multifrontal Cholesky: the same iterates either way
    from lieax.factorgraph import _multifrontal
    from lieax.lstsq import Huber

    graph, _ = noisy_graph(SE3, n=30, loops=40, sigma=0.02, init_sigma=0.05, seed=4)
    graph = graph.with_loss(Huber(3.0))
    assert graph.num_poses * 6 <= factorgraph_module._DENSE_LIMIT
    tight = Termination.gtsam(function_tolerance=1e-10, absolute_function_tolerance=1e-10)
    with monkeypatch.context() as patch:
        patch.setattr(_multifrontal, "native", lambda: False)
        dense = lg.optimize(graph, termination=tight)
    monkeypatch.setattr(factorgraph_module, "_DENSE_LIMIT", 0)
    sparse = lg.optimize(graph, termination=tight)
    methods = {key[2] for key in _optimize._factor_graph(graph, exact=True)._loops}
    assert methods == {"dense", "cholesky"}
    assert sparse.iterations == dense.iterations
    assert sparse.linear_solves == dense.linear_solves
    np.testing.assert_allclose(sparse.cost_history, dense.cost_history, rtol=1e-10)


def test_disconnected_graph_is_reported():
    graph, _ = noisy_graph(SE2, n=6, loops=0)
    keep = np.array([True, True, False, True, True])  # drop edge 2-3: two components
    split = lg.PoseGraph.create(
        graph.poses, graph.edges[keep], graph.measurements[np.flatnonzero(keep)]
    )
    with pytest.raises(ValueError, match="2 disconnected components"):
        lg.optimize(split)
    _optimize.check_anchored(
        split.with_prior([0, 4]), _optimize.gauge_fixed(split.with_prior([0, 4]))
    )


def test_bad_arguments():
    graph, _ = noisy_graph(SE2, n=4, loops=0)
    with pytest.raises(ValueError, match="linear_solver"):
        lg.optimize(graph, linear_solver="qr")
    with pytest.raises(ValueError, match="jacobian"):
        lg.optimize(graph, jacobian="numeric")
    with pytest.raises(ValueError, match="positive definite"):
        lg.PoseGraph.create(graph.poses, graph.edges, graph.measurements, -np.eye(3))
    with pytest.raises(ValueError, match="outside"):
        lg.PoseGraph.create(graph.poses, graph.edges + 1, graph.measurements)


def test_chordal_initialization_beats_odometry():
    graph, truth = noisy_graph(SE3, n=30, loops=12, sigma=0.02, seed=5)
    odometry = lg.spanning_tree_poses(graph)
    chordal = lg.chordal_initialization(graph)
    np.testing.assert_allclose(chordal[0].parameters(), graph.poses[0].parameters(), atol=1e-12)
    assert float(lg.cost(graph, chordal)) < float(lg.cost(graph, odometry))
    rotation_error = np.linalg.norm(np.asarray(chordal.rminus(truth))[:, 3:], axis=1)
    assert rotation_error.max() < 0.1


# ---- real data against GTSAM ---------------------------------------------------------------------


@needs_data
@pytest.mark.parametrize(
    "name", ["tinyGrid3D.g2o", "smallGrid3D.g2o", pytest.param("intel.g2o", marks=pytest.mark.slow)]
)
def test_matches_gtsam_on_shared_sets(name):
    graph = lg.read_g2o(os.path.join(G2O, name))
    expected_cost, expected_iterations = GTSAM_REFERENCE[name]
    result = lg.optimize(graph)
    assert result.status == lieax.Status.CONVERGED
    assert relative_close(result.cost, expected_cost, 1e-6)
    assert result.iterations == expected_iterations


def test_between_and_prior_factors_build_the_optimized_graph():
    """`between_factor` / `prior_factor` are the `Factor` kinds `to_factor_graph` and `optimize`
    solve: a graph built from them by hand reaches `optimize`'s iterates and cost."""
    from lieax.factorgraph import FactorGraph, Var

    graph, _ = noisy_graph(SE2, n=8, loops=3, seed=2)
    graph = graph.with_prior([0])
    b, p = graph.between, graph.priors
    poses = Var(graph.poses, name="poses")
    factors = [
        lg.between_factor(poses[b.i], poses[b.j], b.measured, sqrt_information=b.sqrt_information),
        lg.prior_factor(poses[p.index], p.measured, sqrt_information=p.sqrt_information),
    ]
    result = FactorGraph(factors).solve()
    expected = lg.optimize(graph)
    assert int(result.iterations) == expected.iterations
    assert relative_close(float(result.cost), expected.cost, 1e-10)
    with pytest.raises(ValueError, match="needs closed_form"):
        lg.between_factor(poses[b.i], poses[b.j], b.measured, closed_form=False, exact=False)
