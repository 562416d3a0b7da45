"""A user's script written as the docs write lieax: a type checker must see lieax's types in it
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
from typing import assert_type, reveal_type

import jax
import jax.numpy as jnp
import numpy as np

import lieax
from lieax import S2, SE2, SE3, SE23, SO2, SO3, Sim3, cameras, conventions, io

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
