"""A user's script written as the docs (and examples/icp_demo.py) write lieax: a type checker must see lieax's types in it
(`assert_type`), report no error, and reject the mistakes in `_rejected` (each line's
`# type: ignore[...]` is then used; with `warn_unused_ignores` an unused one is an error, so a hint
that decays to `Any` fails the check). From the repository root, with mypy in any environment:

    mypy --python-executable .venv/bin/python --config-file tests/typecheck/mypy.ini \
        tests/typecheck/user_script.py

(`--python-executable`: an interpreter with lieax's dependencies; lieax itself is read from this
checkout.) It also runs as a script: `python tests/typecheck/user_script.py`.
"""

import os
import tempfile
from typing import Any, assert_type, reveal_type

import jax
import jax.numpy as jnp
import numpy as np

import lieax
from lieax import (
    S2,
    SE2,
    SE3,
    SE23,
    SO2,
    SO3,
    Sim3,
    cameras,
    conventions,
    icp,
    io,
    retractions,
    viz,
)
from lieax.factorgraph import Factor, FactorGraph, SolveResult, Var, VarRef, marginal_covariances
from lieax.lstsq import GaussNewton, LevenbergMarquardt, Solution, Termination

jax.config.update("jax_enable_x64", True)

# ---- getting-started.md ----
T_world_body = lieax.SE3.exp(jnp.array([1.0, 0.0, 0.5, 0.1, -0.2, 0.3]))
reveal_type(SE3.exp(jnp.zeros(6)))
assert_type(T_world_body, SE3)
p_body = jnp.array([0.2, -0.1, 1.0])
p_world = T_world_body @ p_body
assert_type(p_world, jax.Array)
J_T, J_p = lieax.jacobian(lambda T, p: T @ p, argnums=(0, 1))(T_world_body, p_body)
delta = 1e-6 * jnp.array([1.0, -2.0, 0.5, 0.3, 0.1, -0.4])
moved = T_world_body.rplus(delta) @ p_body
assert jnp.allclose(moved - p_world, J_T @ delta, atol=1e-12)
assert jnp.allclose(J_p, T_world_body.rotation().as_matrix())
assert jnp.allclose(T_world_body.rplus(delta).rminus(T_world_body), delta)

# ---- groups.md: constructors, operations, tangent maps ----
R = SO3.from_rpy(0.1, -0.2, 0.3)
assert_type(R, SO3)
assert_type(SO3.from_xyzw(np.array([0.0, 0.0, 0.0, 1.0])), SO3)
assert_type(R.as_xyzw(), jax.Array)
assert_type(SO3.from_rotvec(jnp.array([0.1, 0.2, 0.3])).as_rpy(), jax.Array)
T = SE3.from_rotation_and_translation(R, jnp.array([1.0, 2.0, 3.0]))
assert_type(T, SE3)
X, Y = SE3.sample_uniform(jax.random.key(0), (5,)), SE3.identity((5,))
assert_type(X @ Y, SE3)
assert_type(X.compose(Y).inverse().between(Y), SE3)
assert_type(X.log(), jax.Array)
assert_type(X.interpolate(Y, 0.5), SE3)
assert_type(X.adjoint(), jax.Array)
assert_type(SE3.from_matrix(X.as_matrix()), SE3)
assert_type(SE3.hat(X.log()), jax.Array)
assert_type(SE3.vee(SE3.hat(X.log())), jax.Array)
assert_type(SE3.right_jacobian(X.log()), jax.Array)
assert_type(SE3.left_jacobian_inverse(X.log()), jax.Array)
assert_type(X[0], SE3)
assert_type(X.batch_shape, tuple[int, ...])
assert_type(X.translation(), jax.Array)
assert_type(X.rotation(), SO3)
assert_type(X.bearing(Y), S2)
assert_type(X.range(jnp.zeros(3)), jax.Array)
q, jr = SO3.exp_and_right_jacobian(jnp.array([0.1, 0.2, 0.3]))
assert_type(q, SO3)
w, jri = q.log_and_right_jacobian_inverse()
assert_type(w, jax.Array)
pose2 = SE2.from_xy_theta(1.0, 2.0, 0.3)
assert_type(pose2.bearing(jnp.array([1.0, 1.0])), SO2)
assert_type(pose2.as_xy_theta(), jax.Array)
assert_type(SO2.from_angle(0.3).as_angle(), jax.Array)
assert_type(SE23.from_pose_and_velocity(T, jnp.zeros(3)).pose(), SE3)
S = Sim3.from_se3(T, 2.0)
assert_type(S, Sim3)
assert_type(S.scale(), jax.Array)
direction = S2.from_vector(jnp.array([0.0, 0.0, 1.0]))
assert_type(direction.rotate(R).rplus(jnp.array([0.1, 0.0])), S2)
assert_type(direction.rminus(direction), jax.Array)

# align: an SE3 by default, a Sim3 with scale
a = jnp.array(np.random.default_rng(0).normal(size=(10, 3)))
assert_type(lieax.align(a, T @ a), SE3)
assert_type(lieax.align(a, T @ a, with_scale=True), Sim3)
assert_type(SE3.align(a, T @ a), SE3)
assert_type(SE3.align(a, T @ a).compose(T), SE3)

# ---- autodiff ----
tree = {"pose": T, "offset": jnp.zeros(3)}
zero = lieax.zero_tangents(tree)
moved_tree = lieax.rplus(tree, zero)
assert lieax.tangent_dim(tree) == 9
flat = lieax.flatten_tangents(zero)
assert_type(flat, jax.Array)
back = lieax.unflatten_tangents(tree, flat)
difference = lieax.rminus(moved_tree, tree)
gradient = lieax.grad(lambda T: jnp.sum(T.log() ** 2))(T)
value, jac = lieax.value_and_jacobian(lambda T: T.log())(T)

# ---- conventions ----
xi_gtsam = conventions.se3_tangent_to_gtsam(X.log())
assert_type(xi_gtsam, jax.Array)
assert_type(conventions.se3_from_xyz_xyzw(conventions.se3_to_xyz_xyzw(T)), SE3)
H = conventions.se3_jacobian_to_gtsam(jnp.eye(6), rows=False)
rotation, translation, scale = conventions.sim3_to_gtsam(S)
assert_type(conventions.sim3_from_gtsam(rotation, translation, scale), Sim3)
assert_type(conventions.gtsam_local_coordinates(T, T), jax.Array)
assert_type(conventions.left_from_right_tangent(T, jnp.zeros(6)), jax.Array)
assert_type(conventions.left_from_right_jacobian(jnp.eye(6), at=T, value=T), jax.Array)
assert_type(conventions.s2_tangent_to_gtsam(direction, jnp.zeros(2)), jax.Array)
assert_type(conventions.wxyz_to_xyzw(R.wxyz), jax.Array)

# ---- cameras ----
K = jnp.array([500.0, 500.0, 0.0, 320.0, 240.0])
T_world_camera = SE3.from_translation(jnp.array([0.0, 0.0, -5.0]))
point = jnp.array([0.1, 0.2, 1.0])
assert_type(cameras.project(T_world_camera, K, point), jax.Array)
pixel, J_pose, J_point, J_calibration = cameras.project_jacobians(T_world_camera, K, point)
residual, (J_r_pose, J_r_point) = cameras.projection_residual_jacobians(
    T_world_camera, point, pixel, K
)
assert_type(cameras.bearing(T_world_camera, point), S2)
assert_type(cameras.bearing_error(T_world_camera, point, direction), jax.Array)
uvv = cameras.stereo_project(T_world_camera, jnp.append(K, 0.1), point)
snavely = cameras.snavely_project(T_world_camera, jnp.array([500.0, 0.0, 0.0]), point)
assert_type(snavely, jax.Array)

# ---- io ----
with tempfile.TemporaryDirectory() as directory:
    path = os.path.join(directory, "cloud.ply")
    io.write_ply(path, np.asarray(a), normals=np.asarray(a))
    cloud = lieax.read_point_cloud(path)
    assert_type(cloud, io.PointCloudData)
    assert_type(cloud.points, np.ndarray)
    assert cloud.normals is not None
    lieax.write_pcd(os.path.join(directory, "cloud.pcd"), cloud.points, binary=False)
    assert_type(lieax.read_pcd(os.path.join(directory, "cloud.pcd")).points, np.ndarray)

# ---- ba ----
synthetic = lieax.ba.synthetic_bal(4, 10, 30)
pose, intrinsics = synthetic.problem.camera_variables(np.float64)
assert_type(pose, SE3)
assert_type(
    synthetic.problem.with_parameters(synthetic.truth.cameras, synthetic.truth.points),
    lieax.ba.BALProblem,
)

# ---- factor-graphs.md ----
fx, fy, ftheta = np.arange(5.0), 0.1 * np.arange(5.0), 0.2 * np.arange(5.0)
marks = np.array([[1.0, 2.0], [3.0, -1.0], [4.5, 1.5]])
fi, fj = np.arange(4), np.arange(1, 5)
seen_by, seen = np.array([0, 1, 2, 2, 3, 4]), np.array([0, 0, 1, 2, 1, 2])


def in_frame(k, xy):  # points xy (m, 2) in the frames of poses k (m,)
    c, s = np.cos(ftheta[k]), np.sin(ftheta[k])
    dx, dy = xy[:, 0] - fx[k], xy[:, 1] - fy[k]
    return np.stack([c * dx + s * dy, -s * dx + c * dy], axis=1)


step_x, step_y = in_frame(fi, np.stack([fx[fj], fy[fj]], axis=1)).T
odometry = SE2.from_xy_theta(step_x, step_y, ftheta[fj] - ftheta[fi])
sightings = in_frame(seen_by, marks[seen])
poses = Var(SE2.from_xy_theta(fx + 0.1, fy - 0.1, ftheta + 0.1), name="poses")
points = Var(marks + 0.3, name="points")
assert_type(poses[fi], VarRef)


def between(a, b, z):
    return z.between(a.between(b)).log()


def prior(pose, z):
    return z.between(pose).log()


def landmark(pose, p, z):
    return pose.inverse() @ p - z


factor_graph = FactorGraph([
    Factor(between, (poses[fi], poses[fj]), odometry, sqrt_information=np.diag([10.0, 10.0, 20.0])),
    Factor(prior, (poses[np.array([0])],), SE2.from_xy_theta(fx[:1], fy[:1], ftheta[:1]),
           information=1e4 * np.eye(3)),
    Factor(landmark, (poses[seen_by], points[seen]), sightings, loss=lieax.lstsq.Huber(0.5)),
])  # fmt: skip
solved = factor_graph.solve(eliminate=points)
assert_type(solved, SolveResult)
assert_type(solved.cost, jax.Array)
assert_type(solved.converged, jax.Array)
solved_poses, solved_points = solved.values
assert solved.converged and jnp.allclose(solved_points, marks, atol=1e-8)
assert_type(marginal_covariances(factor_graph, solved.values, points, [0]), np.ndarray)
assert_type(factor_graph.cost(solved.values), jax.Array)
assert_type(factor_graph.index(points), int)
fg_cost, fg_diagonal, fg_off_diagonal, fg_gradient = factor_graph.linearize()
assert_type(fg_diagonal, tuple[jax.Array, ...])
marquardt = LevenbergMarquardt.gtsam(scaling="clipped", damping_update="nielsen")
assert_type(
    factor_graph.solve(solver=marquardt, termination=Termination.gtsam(max_iterations=50)),
    SolveResult,
)
assert_type(
    Factor.make(prior, (poses[[0]],), SE2.from_xy_theta(fx[:1], fy[:1], ftheta[:1])), Factor
)
count, labels = lieax.factorgraph.connected_components(3, [0], [1])
assert_type(count, int)
assert_type(lieax.factorgraph.square_root_information(np.eye(3)), np.ndarray)

# ---- pose graphs (examples/pose_graph.py, landmark_slam.py) ----
square = SE2.from_xy_theta(
    jnp.array([0.0, 1.0, 1.0, 0.0]), jnp.array([0.0, 0.0, 1.0, 1.0]), jnp.arange(4) * np.pi / 2
)
edges = np.array([[0, 1], [1, 2], [2, 3], [3, 0]])
measured = square[edges[:, 0]].between(square[edges[:, 1]])
pose_graph = lieax.graph.PoseGraph.create(square, edges, measured, np.eye(3))
assert_type(pose_graph, lieax.graph.PoseGraph)
with tempfile.TemporaryDirectory() as directory:
    g2o_path = os.path.join(directory, "square.g2o")
    lieax.graph.write_g2o(g2o_path, pose_graph)
    pose_graph = lieax.graph.read_g2o(g2o_path)
assert_type(lieax.graph.chordal_initialization(pose_graph), SE2 | SE3)
pose_graph = pose_graph.with_poses(lieax.graph.chordal_initialization(pose_graph))
optimized = lieax.graph.optimize(pose_graph, termination=Termination.gtsam(max_iterations=20))
assert_type(optimized, lieax.graph.OptimizeResult)
assert_type(optimized.poses, SE2 | SE3)
assert_type(optimized.cost_history, np.ndarray)
print(optimized.status.name, optimized.iterations, optimized.status_name)
assert_type(lieax.graph.cost(pose_graph, optimized.poses), jax.Array)
assert_type(pose_graph.with_prior(0).with_fixed([1]).with_loss(lieax.lstsq.Huber(1.0)),
            lieax.graph.PoseGraph)  # fmt: skip
assert_type(pose_graph.components()[0], int)
graph_factors, pose_var = lieax.graph.to_factor_graph(pose_graph, fixed=[0])
assert_type(graph_factors, FactorGraph)
assert_type(pose_var, Var)
gps = lieax.graph.prior_factor(pose_var[[2]], square[2:3], sqrt_information=np.eye(3))
loop = lieax.graph.between_factor(pose_var[[0]], pose_var[[2]], square[0:1].between(square[2:3]))
assert_type(FactorGraph([*graph_factors.factors, gps, loop]).solve().values, tuple[Any, ...])
assert_type(
    lieax.graph.between_jacobians(square[0], square[1], measured[0]),
    tuple[jax.Array, jax.Array, jax.Array],
)
landmarks = Var(jnp.array([[2.0, 0.5]]), name="landmarks")
sighting = lieax.graph.bearing_range_factor(
    pose_var[[0, 1]], landmarks[[0, 0]], jnp.array([0.2, 1.0]), jnp.array([2.0, 1.1]),
    sigmas=(0.05, 0.1),
)  # fmt: skip
assert_type(sighting, Factor)

# ---- imu.md ----
imu_params = lieax.imu.ImuParams.make_u(
    9.81, accel_noise_density=0.01, gyro_noise_density=0.001, integration_sigma=1e-4
)
accel = jnp.tile(jnp.array([0.1, 0.0, 9.81]), (20, 1))
gyro = jnp.tile(jnp.array([0.0, 0.0, 0.1]), (20, 1))
pim = lieax.imu.preintegrate(imu_params, jnp.zeros(6), accel=accel, gyro=gyro, dt=0.005)
assert_type(pim, lieax.imu.Preintegrated)
assert_type(pim.delta_R, SO3)
assert_type(pim.residual_covariance(), jax.Array)
pose_j, velocity_j = lieax.imu.predict(pim, SE3.identity(), jnp.zeros(3), jnp.zeros(6), imu_params)
assert_type(pose_j, SE3)
intervals = lieax.imu.preintegrate_intervals(
    imu_params, accel=[accel, accel[:15]], gyro=[gyro, gyro[:15]], dt=0.005
)
assert_type(intervals, lieax.imu.Preintegrated)
walk = lieax.imu.BiasRandomWalk.isotropic(1e-3, 1e-4)
combined, combined_covariance = lieax.imu.preintegrate_intervals(
    imu_params, accel=[accel, accel[:15]], gyro=[gyro, gyro[:15]], dt=0.005, walk=walk
)
assert_type(combined_covariance, jax.Array)
imu_poses = Var(SE3.identity((3,)), fixed=[0], name="poses")
velocities, biases = (
    Var(jnp.zeros((3, 3)), name="velocities"),
    Var(jnp.zeros((3, 6)), name="biases"),
)
ki, kj = np.array([0, 1]), np.array([1, 2])
imu = lieax.imu.imu_factor(
    intervals, imu_params, imu_poses[ki], velocities[ki], imu_poses[kj], velocities[kj], biases[ki]
)
assert_type(imu, Factor)
bias_walk = lieax.imu.bias_random_walk_factor(biases[ki], biases[kj], [0.1, 0.075], 1e-3, 1e-4)
assert_type(bias_walk, Factor)

# ---- solvers.md: least_squares ----
samples = jnp.linspace(0.0, 1.0, 20)


def curve(x, t):
    return x["scale"] * jnp.exp(-x["rate"] * t) - 2.0 * jnp.exp(-0.5 * t)


fit = lieax.lstsq.least_squares(curve, {"scale": 1.0, "rate": 1.0}, samples)
assert_type(fit, Solution)
assert_type(fit.cost, jax.Array)
assert fit.converged
fit = lieax.lstsq.least_squares(
    curve, fit.value, samples, solver=GaussNewton(divergence_factor=1e3),
    termination=Termination(max_iterations=5), loss=lieax.lstsq.Huber(1.0),
)  # fmt: skip
damped = LevenbergMarquardt(initial_damping=1e-3)
assert_type(damped.scale(damped.init(3, jnp.float64)), jax.Array)
# ---- icp.md, examples/icp_demo.py and batch_icp.py (small clouds) ----
source_j, target_j, target_normals, T_truth = icp.synthetic_pair(600, rotation_deg=5.0, seed=1)
assert_type(T_truth, SE3)
assert_type(icp.synthetic_scene(600)[0], jax.Array)
# NumPy until the registration, as the demo
source, target = np.asarray(source_j), np.asarray(target_j)
result = icp.point_to_plane(
    source, target, target_normals=target_normals, max_correspondence_distance=0.1,
    max_iterations=np.int64(30), presample=0,
)  # fmt: skip
assert_type(result, icp.ICPResult)
assert_type(result.transform, SE3)
assert_type(result.fitness, jax.Array)
assert_type(result.inlier_rmse, jax.Array)
assert_type(result.iterations, jax.Array)
assert_type(result.status, jax.Array)
assert_type(result.correspondences, jax.Array)
assert result.status_name == "CONVERGED", result
assert_type(
    icp.point_to_point(
        source, target, max_correspondence_distance=0.1, init=result.transform,
        loss=lieax.lstsq.Huber(0.05), search="kdtree",
    ),
    icp.ICPResult,
)  # fmt: skip
assert_type(icp.estimate_normals(target, k=10, viewpoint=None), jax.Array)
assert_type(icp.estimate_covariances(target, k=10), jax.Array)
assert_type(
    icp.gicp(source, target, max_correspondence_distance=0.1, covariances_k=10), icp.ICPResult
)
assert_type(icp.voxel_downsample(target, 0.05), jax.Array)
cells, cells_mask = icp.voxel_downsample(target, 0.05, size=200)
assert_type(cells_mask, jax.Array)
pyramid = icp.multi_scale(
    source, target, voxel_sizes=(0.1, None), max_correspondence_distances=(0.3, 0.1),
    max_iterations=(10, 20),
)  # fmt: skip
assert_type(pyramid, icp.ICPResult)
finest, levels = icp.multi_scale(
    source, target, voxel_sizes=[0.1], max_correspondence_distances=[0.3], return_levels=True
)
assert_type(levels, list[icp.ICPResult])
index = icp.build_index(target, search="brute")
assert_type(icp.nearest(index, source, radius=0.1), icp.Neighbors)
assert_type(icp.nearest(index, source).distance, jax.Array)
sources, source_masks = icp.pad_clouds([source[:500], source])
targets, target_masks = icp.pad_clouds([target, target[:550]])
register = lambda s, sm, t, tm: icp.point_to_plane(
    s, t, source_mask=sm, target_mask=tm, max_correspondence_distance=0.1, throw=False
)  # fmt: skip
batch = jax.vmap(register)(sources, source_masks, targets, target_masks)
assert_type(register(source, None, target, None), icp.ICPResult)

# ---- retractions (groups.md) ----
assert_type(retractions.cayley.rminus(T, T), jax.Array)
assert_type(retractions.first_order, retractions.Retraction)
moved_cayley = lieax.rplus({"pose": T}, {"pose": jnp.zeros(6)}, retraction=retractions.cayley)

# ---- viz (matplotlib without pyplot, as the examples save figures) ----
from matplotlib.figure import Figure  # noqa: E402

figure = Figure()
ax = viz.plot_registration(source, target, result.transform, ax=figure.add_subplot(projection="3d"))
viz.plot_frames(SE3.identity((2,)), ax=ax, origin_color="k", labels=["a", "b"])
viz.plot_points(target, ax=ax, color="tab:green", mask=np.ones(600, bool))
viz.plot_pose_graph(SE3.identity((3,)), edges=np.array([[0, 1], [1, 2]]), ax=ax, frames=0.1)
viz.set_axes_equal(ax)
viz.plot_cost(np.array([3.0, 2.0, 1.0]), ax=figure.add_subplot())

# ---- the compilation cache, threads ----
cache = lieax.enable_compilation_cache(tempfile.mkdtemp())
with lieax.threads(1):
    pass


def _rejected() -> None:
    """Mistakes a checker must report (never called)."""
    T.compose(SO3.identity())  # type: ignore[arg-type]
    T.rotation().translation()  # type: ignore[attr-defined]
    cameras.project(SO3.identity(), K, point)  # type: ignore[arg-type]
    lieax.align(a, a).scale()  # type: ignore[attr-defined]
    lieax.read_ply(3.0)  # type: ignore[arg-type]
    lieax.tangent_dim(T).upper()  # type: ignore[attr-defined]
    Var(SE2.identity((2,)), fixed="first")  # type: ignore[arg-type]
    Factor(between, poses[fi])  # type: ignore[arg-type]
    factor_graph.solve(eliminate=3)  # type: ignore[arg-type]
    lieax.graph.optimize(factor_graph)  # type: ignore[arg-type]
    lieax.imu.preintegrate(imu_params, accel=accel, gyro=gyro)  # type: ignore[call-arg]
    lieax.imu.predict(pim, SE2.identity(), jnp.zeros(3), jnp.zeros(6), imu_params)  # type: ignore[arg-type]
    lieax.lstsq.least_squares(curve, {}, solver="lm")  # type: ignore[arg-type]
    LevenbergMarquardt(damping=1.0)  # type: ignore[call-arg]
    icp.point_to_plane(a, a, max_correspondence_distance=0.1, init=SO3.identity())  # type: ignore[arg-type]
    icp.point_to_point(a, a, max_correspondence_distance=0.1, loss=2.0)  # type: ignore[arg-type]
    icp.point_to_point(a, a, max_correspondence_distance=0.1).transform.scale()  # type: ignore[attr-defined]
    _ = icp.voxel_downsample(a, 0.1, size=10).shape  # type: ignore[attr-defined]
    levels = icp.multi_scale(
        a, a, voxel_sizes=[0.1], max_correspondence_distances=[1.0], return_levels=True
    )
    _ = levels.transform  # type: ignore[attr-defined]
    _ = icp.synthetic_pair(10)[3].shape  # type: ignore[attr-defined]
    icp.nearest(a, a)  # type: ignore[arg-type]
    viz.plot_frames(a)  # type: ignore[arg-type]
