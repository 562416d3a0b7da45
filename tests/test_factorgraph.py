"""Tests of lieax.factorgraph: pose graphs with a GPS prior against `lieax.lstsq`, g2o graphs
against `lieax.graph.optimize`, landmarks (two variable kinds, three factor kinds), a small
bundle adjustment with every linear solver and the Schur complement, the assembled gradient
against finite differences, bad input, marginal covariances (dense inverse, GTSAM), `vmap` over
problems, implicit derivatives with respect to factor data, and the segment sums of the assembly.

Real data from `$LIEAX_DATA_DIR/g2o` is optional (those cases skip without it). Problems are
built once per module (fixtures) so that each structure compiles its loop once.
"""

import os
import warnings

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from _compilations import compilations

from lieax import SE2, SE3, lstsq
from lieax import graph as lg
from lieax.factorgraph import Factor, FactorGraph, Var, marginal_covariances
from lieax.factorgraph._block_pattern import dense_matrix
from lieax.factorgraph._linear import to_padded
from lieax.factorgraph._segments import segment_sum
from lieax.factorgraph._solve import retract
from lieax.lstsq import Termination

jax.config.update("jax_enable_x64", True)

DATA = os.environ.get("LIEAX_DATA_DIR")
G2O = None if DATA is None else os.path.join(DATA, "g2o")
needs_data = pytest.mark.skipif(
    G2O is None or not os.path.isdir(G2O), reason="LIEAX_DATA_DIR/g2o not available"
)


# ---- problems --------------------------------------------------------------------------------


def between(a, b, z):
    return z.between(a.between(b)).log()


def gps(x, p):
    return x.translation() - p


def chain(n=8, seed=0):
    """SE2 poses along a curve: truth, noisy odometry and GPS, a perturbed start."""
    rng = np.random.default_rng(seed)
    xi = rng.normal(size=(n, 3)) * 0.3
    xi[:, 0] += np.arange(n)
    truth = SE2.exp(jnp.asarray(xi))
    i = np.r_[np.arange(n - 1), 0, 2]
    j = np.r_[np.arange(1, n), n - 1, min(5, n - 1)]
    measured = truth[i].between(truth[j]).rplus(jnp.asarray(rng.normal(size=(len(i), 3)) * 0.05))
    position = truth.translation() + rng.normal(size=(n, 2)) * 0.1
    start = truth.rplus(jnp.asarray(rng.normal(size=(n, 3)) * 0.1))
    return truth, i, j, measured, position, start


@pytest.fixture(scope="module")
def gps_graph():
    _, i, j, measured, position, start = chain()
    poses = Var(start, name="poses")
    odometry = Factor(
        between,
        (poses[i], poses[j]),
        measured,
        sqrt_information=np.diag([20.0, 20.0, 50.0]),
        name="between",
    )
    fix = Factor(
        gps,
        (poses[np.arange(len(position))],),
        jnp.asarray(position),
        sqrt_information=10.0 * np.eye(2),
        name="gps",
    )
    graph = FactorGraph([odometry, fix])
    return graph, poses, (i, j, measured, position, start)


def test_pose_graph_with_gps_matches_lstsq(gps_graph):
    graph, _, (i, j, measured, position, start) = gps_graph
    result = graph.solve(
        termination=Termination.gtsam(function_tolerance=1e-12, absolute_function_tolerance=1e-14)
    )
    assert result.status_name == "CONVERGED"

    def residuals(x, _):
        r1 = jax.vmap(between)(x[i], x[j], measured) * jnp.array([20.0, 20.0, 50.0])
        r2 = 10.0 * (x.translation() - position)
        return r1, r2

    reference = lstsq.least_squares(
        residuals, start, termination=Termination(max_iterations=50, function_tolerance=1e-14)
    )
    np.testing.assert_allclose(result.cost, reference.cost, rtol=1e-9)
    np.testing.assert_allclose(result.values[0].rminus(reference.value), 0.0, atol=1e-7)
    # the cost history starts at the initial cost and decreases
    history = np.asarray(result.cost_history)[: int(result.iterations) + 1]
    np.testing.assert_allclose(history[0], graph.cost(), rtol=1e-12)
    assert np.all(np.diff(history) <= 0)


@pytest.mark.parametrize(
    "options",
    [
        {"linear_solver": "cholesky"},
        {"linear_solver": "cg"},
        {"solver": lstsq.LevenbergMarquardt.gtsam(scaling="clipped", damping_update="nielsen")},
        {"solver": lstsq.LevenbergMarquardt.ceres()},
        {"solver": lstsq.GaussNewton()},
    ],
)
def test_solver_options_reach_the_same_cost(gps_graph, options):
    graph, _, _ = gps_graph
    reference = graph.solve(
        termination=Termination.gtsam(function_tolerance=1e-12, absolute_function_tolerance=1e-14)
    )
    result = graph.solve(
        termination=Termination.gtsam(function_tolerance=1e-12, absolute_function_tolerance=1e-14),
        **options,
    )
    assert result.status_name == "CONVERGED"
    np.testing.assert_allclose(result.cost, reference.cost, rtol=1e-7)


def noisy_pose_graph(n=12, seed=1):
    rng = np.random.default_rng(seed)
    xi = rng.normal(size=(n, 6)) * 0.3
    xi[:, 0] += np.arange(n)
    truth = SE3.exp(jnp.asarray(xi))
    i = np.r_[np.arange(n - 1), 0, 3, 5]
    j = np.r_[np.arange(1, n), n - 1, 9, 11]
    measured = truth[i].between(truth[j]).rplus(jnp.asarray(rng.normal(size=(len(i), 6)) * 0.05))
    start = truth.rplus(jnp.asarray(rng.normal(size=(n, 6)) * 0.1))
    information = np.diag(rng.uniform(0.5, 2.0, size=6)) / 0.05**2
    return lg.PoseGraph.create(
        start, np.stack([i, j], 1), measured, np.broadcast_to(information, (len(i), 6, 6))
    )


def test_g2o_graph_matches_graph_optimize(tmp_path):
    path = tmp_path / "small.g2o"
    lg.write_g2o(path, noisy_pose_graph())
    graph = lg.read_g2o(path)
    expected = lg.optimize(graph)
    result = lg.to_factor_graph(graph)[0].solve()
    np.testing.assert_allclose(result.cost, expected.cost, rtol=1e-8)
    assert int(result.iterations) == expected.iterations


def test_to_factor_graph_without_a_fixed_pose_when_gps_anchors_it():
    graph = noisy_pose_graph()
    between, poses = lg.to_factor_graph(graph, fixed=None, check_gauge=False)
    assert len(poses.fixed) == 0
    with pytest.raises(ValueError, match="connected components"):
        FactorGraph(between.factors)  # the gauge is free without the GPS factors
    positions = graph.poses.translation() + 0.01
    gps = Factor(
        lambda pose, z: pose.translation() - z,
        (poses[jnp.arange(graph.num_poses)],),
        positions,
        name="gps",
    )
    result = FactorGraph([*between.factors, gps]).solve()
    assert result.status_name == "CONVERGED"
    # pose 0 is free: the GPS offset moves it, where the default gauge would hold it
    assert not np.allclose(result.values[0][0].parameters(), graph.poses[0].parameters())
    with pytest.raises(ValueError, match="fixed must be"):
        lg.to_factor_graph(graph, fixed="first")


@needs_data
@pytest.mark.parametrize(
    "name", ["tinyGrid3D", pytest.param("smallGrid3D", marks=pytest.mark.slow)]
)
def test_real_g2o_matches_graph_optimize(name):
    graph = lg.read_g2o(os.path.join(G2O, f"{name}.g2o"))
    expected = lg.optimize(graph)
    result = lg.to_factor_graph(graph)[0].solve()
    np.testing.assert_allclose(result.cost, expected.cost, rtol=1e-8)
    assert int(result.iterations) == expected.iterations


# ---- landmarks: two variable kinds, three factor kinds ---------------------------------------


def observe(pose, point, z):
    """The landmark in the pose's frame, minus its measurement."""
    return pose.inverse() @ point - z


def prior(pose, z):
    return z.between(pose).log()


@pytest.fixture(scope="module")
def landmarks():
    rng = np.random.default_rng(3)
    truth, i, j, _, _, _ = chain(n=6, seed=3)
    odometry = truth[i].between(truth[j])
    points = jnp.asarray(rng.uniform(-1, 7, size=(5, 2)))
    pose_index = np.repeat(np.arange(6), 3)
    point_index = rng.integers(0, 5, size=18)
    seen = jax.vmap(lambda x, p: x.inverse() @ p)(truth[pose_index], points[point_index])
    poses = Var(truth.rplus(jnp.asarray(rng.normal(size=(6, 3)) * 0.1)), name="poses")
    marks = Var(points + rng.normal(size=(5, 2)) * 0.2, name="points")
    factors = [
        Factor(between, (poses[i], poses[j]), odometry, name="between"),
        Factor(prior, (poses[0],), truth[:1], information=1e4 * np.eye(3), name="prior"),
        Factor(
            observe,
            (poses[pose_index], marks[point_index]),
            seen,
            loss=lstsq.Huber(1.0),
            name="landmark",
        ),
    ]
    return FactorGraph(factors), poses, marks, truth, points


def test_landmarks_two_kinds_three_factors(landmarks):
    graph, _, marks, truth, points = landmarks
    assert np.unique(np.concatenate(graph.plans[2].indices[1:])).size == 5  # all points seen
    results = [
        graph.solve(
            termination=Termination.gtsam(
                function_tolerance=1e-14, absolute_function_tolerance=1e-20
            ),
            **options,
        )
        for options in ({"eliminate": None}, {"eliminate": marks})
    ]
    for result in results:
        assert result.status_name == "CONVERGED"
        assert float(result.cost) < 1e-14  # the measurements are exact
        np.testing.assert_allclose(result.values[0].rminus(truth), 0.0, atol=1e-7)
        np.testing.assert_allclose(result.values[1], points, atol=1e-7)


def tangent_gradient(graph, values, eps=1e-6):
    """Central finite differences of the cost in the tangent coordinates of every instance."""
    layout = graph.layout
    cost = jax.jit(lambda deltas: graph.cost(retract(graph.variables, values, deltas)))
    out = []
    for k, (count, dim) in enumerate(zip(layout.counts, layout.dims)):
        g = np.zeros((count, dim))
        for a in range(count):
            for c in range(dim):
                deltas = [jnp.zeros((n, d)) for n, d in zip(layout.counts, layout.dims)]
                deltas[k] = deltas[k].at[a, c].set(eps)
                plus = cost(deltas)
                deltas[k] = deltas[k].at[a, c].set(-eps)
                minus = cost(deltas)
                g[a, c] = (plus - minus) / (2 * eps)
        out.append(g)
    return out


def test_assembled_gradient_matches_finite_differences(landmarks):
    graph, *_ = landmarks
    values = graph.initial_values
    _, diag, off, grad = graph.linearize(values)
    for g, expected in zip(grad, tangent_gradient(graph, values)):
        np.testing.assert_allclose(g, expected, rtol=1e-6, atol=1e-6)
    # H is symmetric positive definite and equals JᵀWJ built densely (its diagonal blocks
    # are sums of the factors' blocks; checked through the gradient's finite differences)
    dense = np.asarray(
        dense_matrix(graph.layout.pattern, *to_padded(graph.layout, diag, off, grad)[:2])
    )
    np.testing.assert_allclose(dense, dense.T, atol=1e-9)
    assert np.linalg.eigvalsh(dense).min() > 0


# ---- bundle adjustment ------------------------------------------------------------------------


def snavely(camera, point, observation):
    r"""Snavely's camera: $P = R X + t$, $p = -P_{xy}/P_z$, $f(1 + k_1|p|^2 + k_2|p|^4)\,p$."""
    pose, (f, k1, k2) = camera
    p_camera = pose @ point
    p = -p_camera[:2] / p_camera[2]
    n2 = jnp.sum(p**2)
    return f * (1.0 + k1 * n2 + k2 * n2**2) * p - observation


@pytest.fixture(scope="module")
def bundle():
    rng = np.random.default_rng(7)
    cams, pts = 4, 12
    points = rng.uniform(-1, 1, size=(pts, 3))
    xi = np.zeros((cams, 6))
    xi[:, 0] = np.linspace(-1, 1, cams)
    xi[:, 2] = -5.0  # points in front, negative z in the camera (Snavely's convention)
    xi[:, 3:] = rng.normal(size=(cams, 3)) * 0.05
    poses = SE3.exp(jnp.asarray(xi))
    intrinsics = jnp.tile(jnp.array([500.0, 1e-3, 1e-5]), (cams, 1))
    ci, pi = np.meshgrid(np.arange(cams), np.arange(pts), indexing="ij")
    ci, pi = ci.ravel(), pi.ravel()
    obs = jax.vmap(snavely)(
        (poses[ci], intrinsics[ci]), jnp.asarray(points[pi]), jnp.zeros((len(ci), 2))
    )
    obs = obs + rng.normal(size=obs.shape) * 0.5
    start_cameras = (
        poses.rplus(jnp.asarray(rng.normal(size=(cams, 6)) * 1e-3)),
        intrinsics * (1 + rng.normal(size=(cams, 3)) * 1e-3),
    )
    cameras = Var(start_cameras, fixed=[0, 1], name="cameras")
    landmarks = Var(jnp.asarray(points + rng.normal(size=points.shape) * 0.01), name="points")
    factor = Factor(
        snavely, (cameras[ci], landmarks[pi]), obs, loss=lstsq.Cauchy(2.0), name="reprojection"
    )
    return FactorGraph([factor]), cameras, landmarks


@pytest.mark.parametrize(
    "options",
    [
        {"eliminate": "points", "linear_solver": "dense"},
        {"eliminate": "points", "linear_solver": "cholesky"},
        {"eliminate": "points", "linear_solver": "cg"},
        {"eliminate": None, "linear_solver": "cholesky"},
    ],
)
def test_bundle_adjustment_solvers_agree(bundle, options):
    graph, _, landmarks = bundle
    options = dict(options)
    if "eliminate" in options:
        options["eliminate"] = landmarks
    reference = graph.solve(
        linear_solver="dense",
        termination=Termination.gtsam(function_tolerance=1e-12, absolute_function_tolerance=1e-14),
    )
    result = graph.solve(
        termination=Termination.gtsam(function_tolerance=1e-12, absolute_function_tolerance=1e-14),
        **options,
    )
    assert result.status_name == "CONVERGED"
    assert float(result.cost) < 0.5 * float(graph.cost())
    np.testing.assert_allclose(result.cost, reference.cost, rtol=1e-7)
    np.testing.assert_allclose(result.values[1], reference.values[1], atol=1e-5)


def test_bundle_gradient_matches_finite_differences(bundle):
    graph, *_ = bundle
    values = graph.initial_values
    _, _, _, grad = graph.linearize(values)
    expected_grads = tangent_gradient(graph, values, eps=1e-7)
    expected_grads[0][graph.variables[0].fixed] = 0.0  # fixed cameras do not move
    for g, expected in zip(grad, expected_grads):
        scale = np.abs(expected).max()
        np.testing.assert_allclose(g, expected, rtol=1e-5, atol=1e-6 * scale)


# ---- marginals --------------------------------------------------------------------------------


def test_marginals_match_dense_inverse(landmarks):
    """Marginals are blocks of the inverse of the system `linearize` gives at the values, at a
    solution and away from one (the start); they run the solve's own compiled loop, stopped
    after its first evaluation: no program of their own."""
    graph, poses, marks, *_ = landmarks
    result = graph.solve()
    with compilations() as compiled:
        marginal_covariances(graph, result.values, poses, [0])
    assert compiled == []
    # the loop's system at the values it returns, not at the previous iterate
    _, diag, off, grad = graph.linearize(result.values)
    loop = next(iter(graph._prepared.values()))[0]
    params = graph._parameters(lstsq.LevenbergMarquardt.gtsam(), Termination.gtsam(), 1e-8,
                               np.float64)  # fmt: skip
    system = loop(graph.initial_values, graph.data, params)[2]
    for ours, theirs in zip(jax.tree.leaves(system), jax.tree.leaves((diag, off, grad))):
        np.testing.assert_allclose(ours, theirs, rtol=1e-9, atol=1e-9)
    start = graph.initial_values
    _, diag, off, grad = graph.linearize(start)
    dense = np.asarray(
        dense_matrix(graph.layout.pattern, *to_padded(graph.layout, diag, off, grad)[:2])
    )
    block = slice(0, graph.layout.dims[0])
    np.testing.assert_allclose(
        marginal_covariances(graph, start, poses, [0])[0],
        np.linalg.inv(dense)[block, block],
        rtol=1e-9,
    )
    _, diag, off, grad = graph.linearize(result.values)
    layout = graph.layout
    dense = np.asarray(dense_matrix(layout.pattern, *to_padded(layout, diag, off, grad)[:2]))
    inverse = np.linalg.inv(dense)
    D = layout.block_size
    for var, k in ((poses, 0), (marks, 1)):
        d = layout.dims[k]
        for method in ("dense", "cholesky"):
            cov = marginal_covariances(graph, result.values, var, [1, 3], method=method)
            for m, a in enumerate((1, 3)):
                start = (layout.offsets[k] + a) * D
                np.testing.assert_allclose(
                    cov[m], inverse[start : start + d, start : start + d], rtol=1e-8, atol=1e-14
                )


def test_marginals_match_gtsam():
    gtsam = pytest.importorskip("gtsam")
    truth, i, j, measured, _, start = chain(n=5, seed=4)
    sigmas = np.array([0.1, 0.2, 0.05])
    poses = Var(start, name="poses")
    graph = FactorGraph(
        [
            Factor(between, (poses[i], poses[j]), measured, sqrt_information=np.diag(1 / sigmas)),
            Factor(prior, (poses[0],), truth[:1], sqrt_information=np.diag(1 / sigmas)),
        ]
    )
    # marginals are defined at any linearization point: compare at the start (no solve)
    values = graph.initial_values
    ours = marginal_covariances(graph, values, poses)

    def pose2(x):
        c, s, tx, ty = np.asarray(x.parameters())
        return gtsam.Pose2(tx, ty, np.arctan2(s, c))

    factors = gtsam.NonlinearFactorGraph()
    noise = gtsam.noiseModel.Diagonal.Sigmas(sigmas)
    factors.add(gtsam.PriorFactorPose2(0, pose2(truth[0]), noise))
    for a, b, z in zip(i, j, measured):
        factors.add(gtsam.BetweenFactorPose2(int(a), int(b), pose2(z), noise))
    gtsam_values = gtsam.Values()
    for a in range(5):
        gtsam_values.insert(a, pose2(values[0][a]))
    marginals = gtsam.Marginals(factors, gtsam_values)
    for a in range(5):
        np.testing.assert_allclose(ours[a], marginals.marginalCovariance(a), rtol=1e-6, atol=1e-12)


# ---- vmap and implicit derivatives ------------------------------------------------------------


def test_vmapped_solve_equals_single_solves(gps_graph):
    graph, _, (_, _, _, position, _) = gps_graph
    rng = np.random.default_rng(5)
    batch = jnp.asarray(position[None] + rng.normal(size=(3, *position.shape)) * 0.1)
    root = graph.data[1][1]

    def solve(p):
        return graph.solve(data=[None, (p, root, None)], throw=False)

    batched = jax.vmap(solve)(batch)
    for b in range(3):
        single = solve(batch[b])
        np.testing.assert_allclose(batched.cost[b], single.cost, rtol=1e-10)
        assert int(batched.iterations[b]) == int(single.iterations)
        np.testing.assert_allclose(
            batched.values[0][b].parameters(), single.values[0].parameters(), atol=1e-10
        )


def test_implicit_derivative_matches_finite_differences(gps_graph):
    graph, _, (_, _, _, position, _) = gps_graph
    root = graph.data[1][1]
    options = {
        "termination": Termination.gtsam(
            function_tolerance=1e-14, absolute_function_tolerance=1e-20
        ),
        "throw": False,
    }

    def solution(p):
        return graph.solve(data=[None, (p, root, None)], **options)

    base = solution(jnp.asarray(position))
    direction = np.random.default_rng(6).normal(size=position.shape)

    def moved(p):
        return solution(p).values[0].rminus(base.values[0])

    _, tangent = jax.jvp(lambda p: moved(p), (jnp.asarray(position),), (jnp.asarray(direction),))
    eps = 1e-5
    fd = (moved(position + eps * direction) - moved(position - eps * direction)) / (2 * eps)
    np.testing.assert_allclose(tangent, fd, rtol=1e-5, atol=1e-8)
    # reverse mode: the gradient of the final cost and of a solution coordinate
    grad = jax.grad(lambda p: solution(p).values[0].translation()[3, 0])(jnp.asarray(position))
    x = lambda p: solution(p).values[0].translation()[3, 0]
    fd = (x(position + eps * direction) - x(position - eps * direction)) / (2 * eps)
    np.testing.assert_allclose(np.vdot(grad, direction), fd, rtol=1e-5)
    assert np.all(np.isfinite(grad))


# ---- the Schur choice (eliminate="auto") --------------------------------------------------


def landmark_slam(n_poses=200, n_marks=10, seen=0.9, seed=0):
    """2D landmark SLAM: SE2 poses on a circle chained by odometry, a prior on the first, and
    `n_marks` landmarks each seen by about `seen` of the poses (exact measurements)."""
    rng = np.random.default_rng(seed)
    angle = np.linspace(0.0, 2 * np.pi, n_poses)
    xi = np.stack([10 * np.cos(angle), 10 * np.sin(angle), angle + np.pi / 2], -1)
    truth = SE2.exp(jnp.asarray(xi))
    marks = rng.uniform(-12, 12, size=(n_marks, 2))
    pose_index, mark_index = np.nonzero(rng.random((n_poses, n_marks)) < seen)
    i = np.arange(n_poses - 1)
    seen_at = jax.vmap(lambda x, p: x.inverse() @ p)(truth[pose_index], marks[mark_index])
    poses = Var(truth.rplus(jnp.asarray(rng.normal(size=(n_poses, 3)) * 0.05)), name="poses")
    landmarks = Var(jnp.asarray(marks + rng.normal(size=marks.shape) * 0.1), name="landmarks")
    graph = FactorGraph(
        [
            Factor(between, (poses[i], poses[i + 1]), truth[i].between(truth[i + 1])),
            Factor(prior, (poses[0],), truth[:1]),
            Factor(observe, (poses[pose_index], landmarks[mark_index]), seen_at),
        ]
    )
    return graph, landmarks


def few_camera_bundle():
    """Bundle adjustment: 6 cameras, 40 points each seen by 2-3 of them on average
    (`lieax.ba`, exact observations), one camera and one point fixed at the truth (the
    gauge)."""
    from lieax import ba

    generated = ba.synthetic_bal(6, 40, 90, noise=0.0, seed=3)
    problem, truth = generated.problem, generated.truth
    start = problem.with_parameters(
        np.r_[truth.cameras[:1], problem.cameras[1:]], np.r_[truth.points[:1], problem.points[1:]]
    )
    cameras = Var(start.camera_variables(jnp.float64), fixed=[0], name="cameras")
    points = Var(jnp.asarray(start.points), fixed=[0], name="points")
    factor = Factor(
        ba.camera_residual,
        (cameras[problem.camera_indices], points[problem.point_indices]),
        jnp.asarray(problem.observations),
        jacobian_fn=ba.camera_jacobians,
    )
    assert np.mean(np.bincount(problem.point_indices)) <= 3
    return FactorGraph([factor], check_gauge=False), points


TIGHT = {
    "termination": Termination.gtsam(function_tolerance=1e-15, absolute_function_tolerance=0.0),
    "throw": False,
}


def test_auto_elimination_eliminates_points_seen_by_few_cameras():
    graph, points = few_camera_bundle()
    assert graph._eliminated("auto", "auto") == graph.index(points)
    with warnings.catch_warnings():
        warnings.simplefilter("error")  # an explicit elimination that pays says nothing
        forced = graph.solve(eliminate=points, **TIGHT)
    auto, whole = graph.solve(**TIGHT), graph.solve(eliminate=None, **TIGHT)
    assert float(auto.cost) < 1e-20  # exact observations
    for result in (forced, whole):
        assert float(result.cost) < 1e-20
        for a, b in zip(jax.tree.leaves(result.values), jax.tree.leaves(auto.values)):
            np.testing.assert_allclose(a, b, rtol=1e-10, atol=1e-10)


def test_auto_elimination_keeps_landmarks_seen_by_most_poses():
    graph, landmarks = landmark_slam()
    assert graph._eliminated("auto", "auto") is None
    # decided by `_elimination.reduction_bound`, without building the reduced pattern
    assert ("reduced", graph.index(landmarks)) not in graph._schur
    with pytest.warns(
        UserWarning,
        match=r"eliminating 'landmarks'.* cost more .* ms modelled .* against .* ms modelled",
    ):
        forced = graph.solve(eliminate=landmarks, **TIGHT)
    auto = graph.solve(**TIGHT)
    assert float(auto.cost) < 1e-20  # exact measurements
    for a, b in zip(jax.tree.leaves(forced.values), jax.tree.leaves(auto.values)):
        np.testing.assert_allclose(a, b, rtol=1e-10, atol=1e-10)


def test_auto_elimination_choice_follows_the_cost_model():
    """The model's figures: landmarks seen by most poses link every pair of poses in the
    reduced system, whose dense factorization costs more than the whole sparse system's."""
    from lieax.factorgraph._elimination import candidates

    graph, _ = landmark_slam()
    assert candidates(graph.layout) == (1,)  # the poses share factors, the landmarks do not
    eliminated, whole = graph._elimination_cost(1, "auto"), graph._elimination_cost(None, "auto")
    assert eliminated.off_blocks == 200 * 199 // 2 and eliminated.method == "dense"
    assert whole.off_blocks < 0.2 * eliminated.off_blocks and whole.method == "cholesky"
    assert eliminated.total > 5 * whole.total and eliminated.flops > 100 * whole.flops
    with pytest.raises(ValueError, match="eliminate must be a Var, None or 'auto'"):
        graph.solve(eliminate="points")
    # a larger bundle: the points' elimination beats the whole system's lower bound, so the
    # whole is not analysed (nor the cameras' reduced system: its formation alone costs more)
    from lieax import ba

    problem = ba.synthetic_bal(20, 400, 1000, seed=0).problem
    cameras = Var(problem.camera_variables(jnp.float64), name="cameras")
    points = Var(jnp.asarray(problem.points), name="points")
    args = (cameras[problem.camera_indices], points[problem.point_indices])
    bundle = FactorGraph(
        [Factor(ba.camera_residual, args, jnp.asarray(problem.observations))], check_gauge=False
    )
    assert bundle._eliminated("auto", "auto") == 1
    assert ("cost", None, "auto") not in bundle._schur and ("reduced", 0) not in bundle._schur
    eliminated, whole = bundle._elimination_cost(1, "auto"), bundle._elimination_cost(None, "auto")
    assert eliminated.total < whole.total


@pytest.mark.parametrize("seen", [0.15, 0.4, 0.9])
def test_reduction_bound_is_below_the_modelled_cost(seen):
    """`_elimination.reduction_bound` (the largest clique's share of the model) never exceeds the
    modelled cost of the sparse factorization of the reduced system it bounds, on landmark graphs
    from sparse to dense sightings and on a bundle."""
    from lieax.factorgraph._elimination import candidates, factorization_cost, reduction_bound
    from lieax.factorgraph._structure import reduced_layout

    graphs = [landmark_slam(60, 8, seen=seen, seed=1)[0], few_camera_bundle()[0]]
    for graph in graphs:
        for e in candidates(graph.layout):
            reduced = reduced_layout(graph.layout, e, graph._names())
            modelled = factorization_cost(reduced, "cholesky").factorization
            bound = reduction_bound(graph.layout, e)
            assert 0.0 < bound <= modelled
    # the bound is the whole cost where the reduced system is one clique: 5 poses all seeing
    # one landmark, the only links of the reduced system
    graph = landmark_slam(5, 1, seen=1.0, seed=0)[0]
    reduced = reduced_layout(graph.layout, 1, graph._names())
    modelled = factorization_cost(reduced, "cholesky").factorization
    np.testing.assert_allclose(reduction_bound(graph.layout, 1), modelled, rtol=1e-12)


def test_marquardt_damping_with_nielsens_rule():
    """The Marquardt diagonal (`scaling="clipped"`) pairs with Nielsen's λ rule: GTSAM's ×10 / ÷10
    with it alternates between two λ values, a step taken at λ and the next rejected at λ/10
    (with the identity damping GTSAM's rule stays the default, whose iterates
    `lieax.graph.optimize` reproduces: tests/test_graph.py). Both rules reach the exact fit."""
    from lieax import ba

    problem = ba.synthetic_bal(3, 7, 18, noise=0.0, seed=0).problem  # solvable exactly
    cameras = Var(problem.camera_variables(jnp.float64), name="cameras")
    points = Var(jnp.asarray(problem.points), name="points")
    factor = Factor(
        ba.camera_residual,
        (cameras[problem.camera_indices], points[problem.point_indices]),
        jnp.asarray(problem.observations),
        jacobian_fn=ba.camera_jacobians,
    )
    graph = FactorGraph([factor], check_gauge=False)
    options = {"termination": Termination.gtsam(absolute_function_tolerance=0.0), "throw": False}
    marquardt = lstsq.LevenbergMarquardt.gtsam(scaling="clipped", damping_update="nielsen")
    nielsen = graph.solve(solver=marquardt, **options)
    gtsam_rule = graph.solve(solver=lstsq.LevenbergMarquardt.gtsam(scaling="clipped"), **options)
    for result in (nielsen, gtsam_rule):
        assert result.converged and float(result.cost) < 1e-20
    rejected = int(nielsen.linear_solves) - int(nielsen.iterations)
    assert rejected < 0.5 * int(nielsen.linear_solves)


# ---- bad input --------------------------------------------------------------------------------


def test_bad_input_errors():
    _, i, j, measured, position, start = chain(n=5)
    poses = Var(start, name="poses")
    with pytest.raises(ValueError, match=r"'between'.*index 7 .*out of range.*'poses'"):
        FactorGraph(
            [Factor(between, (poses[i], poses[np.r_[j[:-1], 7]]), measured, name="between")]
        )
    with pytest.raises(ValueError, match=r"index -1"):
        FactorGraph([Factor(between, (poses[np.r_[-1, i[1:]]], poses[j]), measured)])
    with pytest.raises(ValueError, match=r"sqrt_information must have shape \(3, 3\)"):
        FactorGraph([Factor(between, (poses[i], poses[j]), measured, sqrt_information=np.eye(2))])
    with pytest.raises(ValueError, match="not symmetric positive semi-definite"):
        Factor(between, (poses[i], poses[j]), measured, information=-np.eye(3))
    with pytest.raises(ValueError, match=r"sqrt_information 2 is not finite"):
        roots = np.tile(np.eye(3), (len(i), 1, 1))
        roots[2] = 0.0
        FactorGraph([Factor(between, (poses[i], poses[j]), measured, sqrt_information=roots)])
    bad = np.array(position)
    bad[3, 1] = np.nan
    with pytest.raises(ValueError, match=r"'gps': data of instance 3 is not finite"):
        FactorGraph([Factor(gps, (poses[np.arange(5)],), bad, name="gps")])
    with pytest.raises(ValueError, match=r"leading axis 4"):
        FactorGraph([Factor(gps, (poses[np.arange(4)],), position, name="gps")])
    with pytest.raises(
        ValueError, match=r"\[0\], priors constraining 0 of 3 .*: their gauge is free"
    ):
        FactorGraph([Factor(between, (poses[i], poses[j]), measured)])
    with pytest.raises(ValueError, match=r"uses variable 'poses'\[2\] for arguments 0 and 1"):
        FactorGraph(
            [Factor(between, (poses[i], poses[np.r_[1, 2, 2, 4, 4, 5][: len(i)] % 5]), measured)],
            check_gauge=False,
        )
    with pytest.raises(ValueError, match=r"index must be a 1-D integer array"):
        Factor(between, (poses[i.astype(float)], poses[j]), measured)
    with pytest.raises(ValueError, match=r"different lengths"):
        Factor(between, (poses[i], poses[j[:-1]]), measured)
    with pytest.raises(ValueError, match=r"residual must be a vector"):
        FactorGraph([Factor(lambda x: x.log()[None], (poses[np.arange(5)],))])
    with pytest.raises(ValueError, match=r"fixed index 9 is out of range"):
        Var(start, fixed=[9])
    graph = FactorGraph(
        [
            Factor(between, (poses[i], poses[j]), measured),
            Factor(gps, (poses[np.arange(5)],), position),
        ]
    )
    with pytest.raises(ValueError, match="cannot eliminate variable kind 'poses'"):
        graph.solve(eliminate=poses)
    with pytest.raises(ValueError, match="linear_solver must be one of"):
        graph.solve(linear_solver="qr")
    with pytest.raises(TypeError, match="linear_solver="):
        graph.solve(solver="dense")
    with pytest.raises(ValueError, match="supports the scalings"):
        graph.solve(solver=lstsq.LevenbergMarquardt(scaling="minpack"))
    with pytest.raises(ValueError, match="supports the damping updates"):
        graph.solve(solver=lstsq.LevenbergMarquardt.gtsam(damping_update="minpack"))
    with pytest.raises(ValueError, match=r"values for 'poses' have shapes"):
        graph.solve(values=[start[:3]])


def test_covariance_whitens_as_its_inverse_information():
    """`covariance=Σ` whitens as `information=Σ⁻¹`: `‖R r‖² = rᵀ Σ⁻¹ r` per instance, and a
    shared diagonal covariance gives `diag(1/σ)`; two noise options, or a covariance that is not
    symmetric positive definite, are refused naming the factor kind and the instance."""
    _, i, j, measured, _, start = chain(n=5)
    poses = Var(start, fixed=[0], name="poses")
    rng = np.random.default_rng(3)
    a = rng.normal(size=(len(i), 3, 3))
    covariance = a @ np.swapaxes(a, 1, 2) + 0.1 * np.eye(3)
    by_covariance = Factor(between, (poses[i], poses[j]), measured, covariance=covariance)
    by_information = Factor(
        between, (poses[i], poses[j]), measured, information=np.linalg.inv(covariance)
    )
    residuals = rng.normal(size=(len(i), 3))

    def whitened_norms(factor):
        return np.linalg.norm(np.einsum("mab,mb->ma", factor.sqrt_information, residuals), axis=1)

    expected = np.sqrt(np.einsum("ma,mab,mb->m", residuals, np.linalg.inv(covariance), residuals))
    np.testing.assert_allclose(whitened_norms(by_covariance), expected, rtol=1e-10)
    np.testing.assert_allclose(whitened_norms(by_information), expected, rtol=1e-10)
    sigmas = np.array([0.1, 0.2, 0.05])
    shared = Factor(between, (poses[i], poses[j]), measured, covariance=np.diag(sigmas**2))
    np.testing.assert_allclose(shared.sqrt_information, np.diag(1 / sigmas), rtol=1e-12)
    with pytest.raises(ValueError, match="not information and covariance"):
        Factor(between, (poses[i], poses[j]), measured, information=np.eye(3), covariance=np.eye(3))
    bad = covariance.copy()
    bad[4] = -np.eye(3)
    with pytest.raises(ValueError, match=r"'odometry': covariance 4 is not symmetric positive"):
        Factor(between, (poses[i], poses[j]), measured, covariance=bad, name="odometry")
    bad[2, 0, 1] += 1.0
    with pytest.raises(ValueError, match=r"'odometry': covariance 2 is not symmetric positive"):
        Factor(between, (poses[i], poses[j]), measured, covariance=bad, name="odometry")


def test_connected_components_match_scipy():
    """The NumPy components of the gauge check label nodes as SciPy's csgraph does: random
    graphs from empty to connected, a long path in reverse order, isolated nodes."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components as scipy_components

    from lieax.factorgraph._structure import connected_components

    rng = np.random.default_rng(11)
    cases = [(1, np.zeros(0, int), np.zeros(0, int)), (500, np.arange(499)[::-1], None)]
    cases += [(n, rng.integers(0, n, m), rng.integers(0, n, m)) for n, m in
              [(7, 0), (50, 20), (300, 200), (300, 600), (2000, 1500)]]  # fmt: skip
    for n, rows, cols in cases:
        cols = rows + 1 if cols is None else cols
        count, labels = connected_components(n, rows, cols)
        adjacency = coo_matrix((np.ones(len(rows)), (rows, cols)), shape=(n, n))
        expected_count, expected = scipy_components(adjacency, directed=False)
        assert count == expected_count
        np.testing.assert_array_equal(labels, expected)


def test_nonfinite_start_raises_or_reports(gps_graph):
    graph, _, (_, _, _, _, start) = gps_graph
    params = np.array(start.parameters())
    params[2, 2] = np.inf
    values = [SE2(jnp.asarray(params))]
    with pytest.raises(lstsq.SolveError, match="NONFINITE"):
        graph.solve(values=values)
    # under jit the error comes when the program runs; throw=False reads the status
    with pytest.raises(Exception, match="SolveError: the factor graph solve ended NONFINITE"):
        jax.block_until_ready(jax.jit(lambda v: graph.solve(values=v))(values))
    result = jax.jit(lambda v: graph.solve(values=v, throw=False))(values)
    assert int(result.status) == lstsq.Status.NONFINITE


def test_solve_staged_by_jit_with_concrete_values(gps_graph):
    """A `jit` of a function that solves from concrete values (the graph's own start, closed
    over) stages the solve: the same result as the eager solve, not a NumPy conversion of a
    traced summary (`TracerArrayConversionError`, before the solve asked JAX's trace state)."""
    graph = gps_graph[0]
    eager = graph.solve()
    cost, values = jax.jit(lambda: (lambda r: (r.cost, r.values))(graph.solve()))()
    assert float(cost) == pytest.approx(float(eager.cost), rel=1e-12)
    np.testing.assert_allclose(
        values[0].parameters(), eager.values[0].parameters(), rtol=0, atol=1e-12
    )


def test_bundle_adjustment_with_lieax_ba():
    ba = pytest.importorskip("lieax.ba")
    problem = ba.synthetic_bal(5, 24, 80, seed=2).problem
    cameras = Var(problem.camera_variables(jnp.float64), fixed=[0], name="cameras")
    points = Var(jnp.asarray(problem.points), fixed=[0], name="points")
    args = (cameras[problem.camera_indices], points[problem.point_indices])
    observed = jnp.asarray(problem.observations)
    closed = FactorGraph(
        [Factor(ba.camera_residual, args, observed, jacobian_fn=ba.camera_jacobians)],
        check_gauge=False,
    )
    autodiff = FactorGraph([Factor(ba.camera_residual, args, observed)], check_gauge=False)
    options = {
        "eliminate": points,
        "linear_solver": "cholesky",
        "termination": Termination.gtsam(function_tolerance=1e-10),
    }
    result = closed.solve(**options)
    reference = autodiff.solve(**options)
    assert result.status_name == "CONVERGED"
    assert float(result.cost) < 0.05 * float(closed.cost())  # down to the pixel noise
    np.testing.assert_allclose(result.cost, reference.cost, rtol=1e-6)


def test_structure_is_analysed_once(gps_graph):
    _, poses, (i, j, measured, position, _) = gps_graph

    def build(shift):  # (built here: the module's graph may have left the structure cache)
        return FactorGraph(
            [
                Factor.make(
                    between,
                    (poses[i], poses[j]),
                    measured,
                    sqrt_information=np.diag([20.0, 20.0, 50.0]),
                ),
                Factor(
                    gps,
                    (poses[np.arange(len(position))],),
                    jnp.asarray(position) + shift,
                    sqrt_information=10.0 * np.eye(2),
                ),
            ]
        )

    graph = build(0.0)
    graph.solve()
    again = build(0.1)
    assert again.layout is graph.layout and again.plans is graph.plans
    loops = dict(graph._loops)
    result = again.solve()
    assert again._loops.keys() == loops.keys()  # the compiled loop was reused
    assert result.status_name == "CONVERGED"


def test_kinds_sharing_a_residual_are_evaluated_once(gps_graph):
    """The between factor split into two kinds of their own information is traced once for
    both, and linearizes as one kind with that information per instance."""
    from lieax.factorgraph._assembly import evaluate

    graph, poses, (i, j, measured, _, _) = gps_graph
    fix = graph.factors[1]
    roots = np.stack([np.diag([20.0, 20.0, 50.0])] * 5 + [np.diag([5.0, 8.0, 30.0])] * (len(i) - 5))
    first, second = slice(0, 5), slice(5, None)
    split = FactorGraph(
        [
            Factor(between, (poses[i[first]], poses[j[first]]), measured[first],
                   sqrt_information=roots[0]),
            Factor(between, (poses[i[second]], poses[j[second]]), measured[second],
                   sqrt_information=roots[5]),
            fix,
        ]
    )  # fmt: skip
    merged = FactorGraph(
        [Factor(between, (poses[i], poses[j]), measured, sqrt_information=roots), fix]
    )

    def evaluated(g):
        return jax.jit(lambda v, d: evaluate(g.factors, g.plans, v, d))(g.initial_values, g.data)

    (cost_split, parts_split), (cost_merged, parts_merged) = evaluated(split), evaluated(merged)
    np.testing.assert_allclose(cost_split, cost_merged, rtol=1e-13)
    for s, t in ((0, slice(0, 5)), (1, slice(5, None))):
        r, blocks, _ = parts_split[s]
        np.testing.assert_allclose(r, parts_merged[0][0][t], rtol=1e-13)
        for b, c in zip(blocks, parts_merged[0][1]):
            np.testing.assert_allclose(b, c[t], rtol=1e-13)

    def equations(g):
        return len(jax.make_jaxpr(lambda v, d: evaluate(g.factors, g.plans, v, d))(
            g.initial_values, g.data).eqns)  # fmt: skip

    # one traced copy of the between factor: the split adds a few slices and products, where a
    # second copy would double the program
    assert equations(split) < 1.3 * equations(merged)


@pytest.mark.parametrize("group", [SE2, SE3])
def test_pose_graph_blocks_match_finite_differences(group):
    """`lieax.graph.to_factor_graph`'s closed-form between and prior blocks against central
    differences in local coordinates and against `lieax.jacobian`, with errors rotating by 0
    (pure translation), 1e-9, 1e-4, 1, π - 1e-4 and π - 1e-6 rad."""
    import lieax
    from lieax.graph._factor_graph import _BLOCKS

    between_blocks, prior_blocks = _BLOCKS[True]

    d = group.tangent_dim
    eps = 1e-6
    steps = jnp.concatenate([eps * jnp.eye(d), -eps * jnp.eye(d)])

    @jax.jit
    def check(x_i, x_j, z):
        _, blocks = between_blocks(x_i, x_j, z)
        auto = lieax.jacobian(lambda a, b: z.between(a.between(b)).log(), (0, 1))(x_i, x_j)
        prior = prior_blocks(x_j, z)[1][0], lieax.jacobian(lambda b: z.between(b).log())(x_j)
        fd = []
        for k, x in enumerate((x_i, x_j)):

            def f(t, k=k, x=x):
                args = [x_i, x_j]
                args[k] = x.rplus(t)
                return between_blocks(*args, z)[0]

            values = jax.vmap(f)(steps)
            fd.append(((values[:d] - values[d:]) / (2 * eps)).T)
        return blocks, auto, prior, fd

    rng = np.random.default_rng(d)
    for angle in (0.0, 1e-9, 1e-4, 1.0, np.pi - 1e-4, np.pi - 1e-6):
        xi = rng.normal(size=(2, d))
        x_i, x_j = group.exp(jnp.asarray(xi[0])), group.exp(jnp.asarray(xi[1]))
        axis = np.ones(1) if d == 3 else rng.normal(size=3)
        err = np.r_[rng.normal(size=2 if d == 3 else 3), angle * axis / np.linalg.norm(axis)]
        z = x_i.between(x_j).rplus(-jnp.asarray(err))  # leaves the error `err`
        blocks, auto, prior, fd = check(x_i, x_j, z)
        for block, expected in zip((*blocks, prior[0]), (*auto, prior[1])):
            np.testing.assert_allclose(block, expected, atol=1e-8)
            assert np.all(np.isfinite(block))
        if angle < np.pi - 1e-3:  # central differences would cross π
            for block, expected in zip(blocks, fd):
                np.testing.assert_allclose(block, expected, atol=1e-6)


# ---- issue 32 ---------------------------------------------------------------------------------


def test_x64_switched_on_after_a_graph_was_built():
    """A graph built in 32-bit mode refuses to run once `jax_enable_x64` is on (it would run in
    float32, or fail on int32 and int64 indices), and the same structure built again in 64-bit
    mode is analysed again and solves in float64 (it took the 32-bit graph's cached structure,
    and its Schur solve failed on `int32` and `int64` indices)."""
    ba = pytest.importorskip("lieax.ba")

    def build():
        problem = ba.synthetic_bal(3, 10, 25, seed=2).problem
        cameras = Var(problem.camera_variables(), fixed=[0], name="cameras")
        points = Var(jnp.asarray(problem.points), fixed=[0], name="points")
        args = (cameras[problem.camera_indices], points[problem.point_indices])
        observed = jnp.asarray(problem.observations)
        factor = Factor(ba.camera_residual, args, observed, jacobian_fn=ba.camera_jacobians)
        return FactorGraph([factor], check_gauge=False), points

    with jax.enable_x64(False):
        narrow, points = build()
        result = narrow.solve(eliminate=points, linear_solver="dense")
        assert result.values[1].dtype == jnp.float32
    with pytest.raises(ValueError, match=r"built with jax_enable_x64=False and is used with"):
        narrow.solve(eliminate=points, linear_solver="dense")
    wide, points = build()
    assert wide.layout is not narrow.layout
    result = wide.solve(eliminate=points, linear_solver="dense")
    assert result.status_name == "CONVERGED" and result.values[1].dtype == jnp.float64


@pytest.mark.parametrize("algorithm", [lstsq.LevenbergMarquardt.gtsam(), lstsq.GaussNewton()])
def test_an_exact_fit_converges_with_absolute_tolerance_zero(algorithm):
    """Noise-free bundle adjustment, gauge fixed at the truth, `absolute_function_tolerance=0`: the cost
    falls to the floating-point floor (about 1e-27 from 323) and the solve ends CONVERGED (it
    ended DIVERGED, damping exhausted on rounding noise, and Gauss-Newton ran to
    MAX_ITERATIONS)."""
    import dataclasses

    ba = pytest.importorskip("lieax.ba")
    generated = ba.synthetic_bal(3, 10, 25, noise=0.0, seed=2)
    cameras, points = generated.problem.cameras.copy(), generated.problem.points.copy()
    cameras[0], points[0] = generated.truth.cameras[0], generated.truth.points[0]
    problem = dataclasses.replace(generated.problem, cameras=cameras, points=points)
    cameras = Var(problem.camera_variables(), fixed=[0], name="cameras")
    points = Var(jnp.asarray(problem.points), fixed=[0], name="points")
    args = (cameras[problem.camera_indices], points[problem.point_indices])
    observed = jnp.asarray(problem.observations)
    graph = FactorGraph(
        [Factor(ba.camera_residual, args, observed, jacobian_fn=ba.camera_jacobians)],
        check_gauge=False,
    )
    result = graph.solve(
        eliminate=points,
        solver=algorithm,
        termination=Termination.gtsam(absolute_function_tolerance=0.0),
    )
    assert result.status_name == "CONVERGED"
    assert float(result.cost) < 1e-18 * float(graph.cost())
    np.testing.assert_allclose(result.values[1], generated.truth.points, atol=1e-9)


def partial_prior_chain(n=6, seed=8):
    """An SE2 chain whose priors on poses 0 and 3 hold positions only (rotation unconstrained,
    GTSAM's zero rotation precision): truth, indices, measurements, start."""
    rng = np.random.default_rng(seed)
    truth, i, j, measured, _, start = chain(n=n, seed=seed)
    anchors = np.array([0, 3])
    priors = truth[anchors].rplus(jnp.asarray(rng.normal(size=(2, 3)) * 0.05))
    return truth, i, j, measured, start, anchors, priors


def test_partial_priors_leave_their_free_directions_free():
    """A prior with `sigmas` inf on the rotation, PSD `information` or a rank-deficient
    `sqrt_information` whiten alike; the gauge check counts only constrained directions (one
    position prior leaves the rotation free: refused; two fix it); the free direction stays
    singular in H; bad partial information is refused naming the factor kind."""
    _, i, j, measured, start, anchors, priors = partial_prior_chain()
    poses = Var(start, name="poses")
    odometry = Factor(between, (poses[i], poses[j]), measured, sigmas=[0.1, 0.1, 0.05])
    sigmas = np.array([0.1, 0.1, np.inf])
    by_sigmas = Factor(prior, (poses[anchors],), priors, sigmas=sigmas, name="position")
    by_information = Factor(
        prior, (poses[anchors],), priors, information=np.diag([100.0, 100.0, 0.0])
    )
    rotated = np.array([[0.6, 0.8, 0.0], [-0.8, 0.6, 0.0], [0.0, 0.0, 1.0]])
    by_root = Factor(
        prior, (poses[anchors],), priors, sqrt_information=rotated @ np.diag([10.0, 10.0, 0.0])
    )
    for f in (by_sigmas, by_information, by_root):  # one information R^T R
        root = np.asarray(f.sqrt_information)
        np.testing.assert_allclose(root.T @ root, np.diag([100.0, 100.0, 0.0]), atol=1e-12)
    result = FactorGraph([odometry, by_sigmas]).solve(
        termination=Termination.gtsam(function_tolerance=1e-12)
    )
    assert result.status_name == "CONVERGED"

    one = Factor(prior, (poses[anchors[:1]],), priors[:1], sigmas=sigmas, name="position")
    with pytest.raises(ValueError, match=r"priors constraining 2 of 3 directions\): their gauge"):
        FactorGraph([odometry, one])
    # with one position prior, H is singular along one direction (the rotation about it)
    graph = FactorGraph([odometry, one], check_gauge=False)
    _, diag, off, grad = graph.linearize()
    dense = np.asarray(
        dense_matrix(graph.layout.pattern, *to_padded(graph.layout, diag, off, grad)[:2])
    )
    eigenvalues = np.linalg.eigvalsh(dense)
    assert abs(eigenvalues[0]) < 1e-10 * eigenvalues[-1] < eigenvalues[1]

    with pytest.raises(ValueError, match=r"'position': sigmas 0 has sigma nan at coordinate 1"):
        Factor(prior, (poses[anchors],), priors, sigmas=[0.1, np.nan, 1.0], name="position")
    with pytest.raises(ValueError, match=r"sigmas 0 is all inf"):
        Factor(prior, (poses[anchors],), priors, sigmas=np.full(3, np.inf))
    with pytest.raises(ValueError, match=r"information 0 is not symmetric positive semi-definite"):
        Factor(prior, (poses[anchors],), priors, information=np.diag([1.0, 1.0, -1e-3]))
    with pytest.raises(ValueError, match="not information and sigmas"):
        Factor(prior, (poses[anchors],), priors, information=np.eye(3), sigmas=np.ones(3))


def test_partial_priors_match_gtsam():
    """Position-only priors (GTSAM's `Diagonal::Precisions` with a zero rotation precision, as
    its KITTI example's first prior) reach GTSAM's optimum and cost."""
    gtsam = pytest.importorskip("gtsam")
    truth, i, j, measured, start, anchors, priors = partial_prior_chain()
    odometry_sigmas = np.array([0.1, 0.1, 0.05])
    poses = Var(start, name="poses")
    graph = FactorGraph(
        [
            Factor(between, (poses[i], poses[j]), measured, sigmas=odometry_sigmas),
            Factor(prior, (poses[anchors],), priors, sigmas=[0.1, 0.1, np.inf]),
        ]
    )
    result = graph.solve(
        termination=Termination.gtsam(function_tolerance=1e-12, absolute_function_tolerance=0.0)
    )
    assert result.status_name == "CONVERGED"

    def pose2(x):
        c, s, tx, ty = np.asarray(x.parameters())
        return gtsam.Pose2(tx, ty, np.arctan2(s, c))

    factors = gtsam.NonlinearFactorGraph()
    noise = gtsam.noiseModel.Diagonal.Sigmas(odometry_sigmas)
    for a, b, z in zip(i, j, measured):
        factors.add(gtsam.BetweenFactorPose2(int(a), int(b), pose2(z), noise))
    position_only = gtsam.noiseModel.Diagonal.Precisions(np.array([100.0, 100.0, 0.0]))
    for a, z in zip(anchors, priors):
        factors.add(gtsam.PriorFactorPose2(int(a), pose2(z), position_only))
    initial = gtsam.Values()
    for a in range(start.batch_shape[0]):
        initial.insert(a, pose2(start[a]))
    parameters = gtsam.LevenbergMarquardtParams()
    parameters.setRelativeErrorTol(1e-12)
    parameters.setAbsoluteErrorTol(0.0)
    solved = gtsam.LevenbergMarquardtOptimizer(factors, initial, parameters).optimize()
    np.testing.assert_allclose(result.cost, factors.error(solved), rtol=1e-8)
    for a in range(start.batch_shape[0]):
        expected = solved.atPose2(a)
        ours = pose2(result.values[0][a])
        np.testing.assert_allclose(
            [ours.x(), ours.y(), ours.theta()],
            [expected.x(), expected.y(), expected.theta()],
            atol=1e-7,
        )


@pytest.mark.parametrize(
    "indices, count, gathered",
    [
        (np.array([0, 2, 2, 1, 0, 2, 4, 1]), 5, True),  # balanced, slot 3 empty
        (np.arange(6)[::-1].copy(), 6, True),  # one term per slot
        (np.r_[np.zeros(40, int), np.arange(1, 8)], 8, False),  # one slot holds most terms
    ],
)
def test_segment_sums_gather_where_slots_are_balanced(indices, count, gathered):
    """`_segments.segment_sum` equals `jax.ops.segment_sum` (to rounding), as one gather with no
    scatter (XLA CPU's serial loop) where the slots hold similar numbers of terms, a scatter
    otherwise; traced indices scatter."""
    terms = np.random.default_rng(0).normal(size=(len(indices), 3, 2))
    expected = jax.ops.segment_sum(terms, indices, count)
    program = jax.jit(lambda t: segment_sum(t, indices, count))
    np.testing.assert_allclose(program(terms), expected, rtol=0, atol=1e-13)
    assert ("scatter" not in program.lower(terms).as_text()) == gathered
    traced = jax.jit(lambda t, i: segment_sum(t, i, count))
    np.testing.assert_allclose(traced(terms, indices), expected, rtol=0, atol=1e-13)
