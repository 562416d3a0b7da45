"""Camera models (`lieax.cameras`): the closed-form Jacobians of the pinhole (`Cal3_S2`,
`Cal3DS2`), stereo and bearing models against `lieax.jacobian` of the value functions (forward
and reverse) and central differences in local coordinates, float64, at the pose regimes
(identity, 1e-9 from it, 1e-4 rad, π - 1e-4, π - 1e-6, random, a pure translation), batched,
vmapped, broadcast and unbatched; Hessians of the value path against differences of its
gradient; values and Jacobians against GTSAM's `PinholeCameraCal3_S2`, `Cal3DS2`,
`StereoCamera` and `BearingFactor3D` when gtsam is installed; the factors and the cheirality
policy on a small bundle adjustment, against GTSAM's default factors."""

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from _stacked import at_zero_and_steps
from scipy.spatial.transform import Rotation

import lieax
from lieax import SE3, SO3, cameras
from lieax import conventions as cv
from lieax import factorgraph as fg
from lieax.lstsq import Termination

_AXIS = np.array([0.3, -0.5, 0.8]) / np.linalg.norm([0.3, -0.5, 0.8])
REGIMES = {
    "identity": np.zeros(3),
    "near-identity-1e-9": 1e-9 * _AXIS,
    "small-1e-4": 1e-4 * _AXIS,
    "near-pi-1e-4": (np.pi - 1e-4) * _AXIS,
    "near-pi-1e-6": (np.pi - 1e-6) * _AXIS,
    "random": np.array([0.7, -1.9, 0.4]),
    "pure-translation": np.zeros(3),
}
CAL3_S2 = np.array([500.0, 510.0, 7.0, 320.0, 240.0])
CAL3DS2 = np.array([500.0, 510.0, 7.0, 320.0, 240.0, 0.11, -0.05, 0.012, -0.021])
STEREO = np.array([500.0, 510.0, 7.0, 320.0, 240.0, 0.54])


def _case(rotvec, seed, pure_translation):
    r"""`(T_world_camera, point, P)` with the point at $P = (a, b, 4)$, $|a|, |b| \le 1$, in the
    camera (in front)."""
    rng = np.random.default_rng(seed)
    P = np.array([*rng.uniform(-1, 1, 2), 4.0])
    point = np.zeros(3) if pure_translation else rng.uniform(-2, 2, 3)
    R = Rotation.from_rotvec(rotvec).as_matrix()
    t = point - R @ P
    return np.concatenate([rotvec, t]), point, P


_CASES = [_case(r, k, name == "pure-translation") for k, (name, r) in enumerate(REGIMES.items())]
ROTVECS = jnp.asarray(np.stack([c[0][:3] for c in _CASES]))
TRANSLATIONS = jnp.asarray(np.stack([c[0][3:] for c in _CASES]))
POINTS = jnp.asarray(np.stack([c[1] for c in _CASES]))
# measured bearings ~0.2 rad from the true ones
BEARINGS = jnp.asarray(
    np.stack([(c[2] / np.linalg.norm(c[2])) + [0.1, -0.15, 0.05] for c in _CASES])
)
BEARINGS = BEARINGS / jnp.linalg.norm(BEARINGS, axis=-1, keepdims=True)


def _pose(rotvec, translation):
    return SE3.from_rotation_and_translation(SO3.exp(rotvec), translation)


# model: (value function, closed form (value, blocks), extra argument, is it differentiated)
MODELS = {
    "Cal3_S2": (
        lambda T, X, K: cameras.project(T, K, X),
        lambda T, X, K: cameras.project_jacobians(T, K, X),
        CAL3_S2,
        True,
    ),
    "Cal3DS2": (
        lambda T, X, K: cameras.project(T, K, X),
        lambda T, X, K: cameras.project_jacobians(T, K, X),
        CAL3DS2,
        True,
    ),
    "stereo": (
        lambda T, X, K: cameras.stereo_project(T, K, X),
        lambda T, X, K: cameras.stereo_project_jacobians(T, K, X),
        STEREO,
        True,
    ),
    "bearing": (cameras.bearing_error, cameras.bearing_error_jacobians, None, False),
}
STEP = 1e-6
HESSIAN_STEP = 1e-5
# the Hessian is checked along these directions (H v by forward over reverse mode)
DIRECTIONS = jnp.asarray(np.random.default_rng(7).normal(size=(3, 18)))


def _extra(name):
    extra = MODELS[name][2]
    return (
        BEARINGS
        if extra is None
        else jnp.broadcast_to(jnp.asarray(extra), (len(_CASES), len(extra)))
    )


@functools.cache
def checks(name):
    """One jitted program per model, vmapped over the regimes: the closed form, `lieax.jacobian`
    in both modes, central differences in local coordinates, and the Hessian of
    $\\tfrac12|f|^2$ along three directions with central differences of its gradient."""
    value, closed, _, differentiated = MODELS[name]
    argnums = (0, 1, 2) if differentiated else (0, 1)

    def one(rotvec, translation, point, extra):
        pose = _pose(rotvec, translation)
        val, *blocks = closed(pose, point, extra)
        closed_J = jnp.concatenate(blocks, -1)
        autodiff = [
            jnp.concatenate(lieax.jacobian(value, argnums, mode=mode)(pose, point, extra), -1)
            for mode in ("fwd", "rev")
        ]
        sizes = (6, 3, extra.shape[-1] if differentiated else 0)

        def moved(delta):
            extra_ = extra + delta[9:] if differentiated else extra
            return value(pose.rplus(delta[:6]), point + delta[6:9], extra_)

        n = sum(sizes)
        zero = jnp.zeros(n)
        value_at_zero, plus_values, minus_values = at_zero_and_steps(moved, STEP * jnp.eye(n))
        columns = (plus_values - minus_values) / (2 * STEP)

        def cost(delta):
            r = moved(delta)
            return 0.5 * jnp.sum(r * r)

        gradient = jax.grad(cost)
        directions = DIRECTIONS[:, :n] / jnp.linalg.norm(DIRECTIONS[:, :n], axis=1, keepdims=True)
        hessian = jax.vmap(lambda v: jax.jvp(gradient, (zero,), (v,))[1])(directions)
        gradient_at_zero, plus, minus = at_zero_and_steps(gradient, HESSIAN_STEP * directions)
        hessian_fd = (plus - minus) / (2 * HESSIAN_STEP)
        return dict(
            value=val,
            value_path=value_at_zero,
            closed=closed_J,
            fwd=autodiff[0],
            rev=autodiff[1],
            fd=columns.T,
            hessian=hessian,
            hessian_fd=hessian_fd,
            gradient=gradient_at_zero,
        )

    out = jax.jit(jax.vmap(one))(ROTVECS, TRANSLATIONS, POINTS, _extra(name))
    return jax.device_get(out)


def _relative(a, b):
    return np.max(np.abs(a - b)) / max(1.0, np.max(np.abs(b)))


@pytest.mark.parametrize("name", list(MODELS))
@pytest.mark.parametrize("regime", list(REGIMES))
def test_closed_form_matches_autodiff_and_differences(name, regime):
    out = {k: v[list(REGIMES).index(regime)] for k, v in checks(name).items()}
    assert np.all(np.isfinite(out["closed"])) and np.all(np.isfinite(out["gradient"]))
    np.testing.assert_allclose(out["value"], out["value_path"], rtol=1e-12, atol=1e-12)
    for mode in ("fwd", "rev"):
        assert _relative(out[mode], out["closed"]) < 1e-10, mode
    assert _relative(out["closed"], out["fd"]) < 1e-7
    assert np.all(np.isfinite(out["hessian"]))
    assert _relative(out["hessian"], out["hessian_fd"]) < 1e-6


@pytest.mark.parametrize("name", list(MODELS))
def test_batched_broadcast_and_unbatched_agree(name):
    _, closed, _, _ = MODELS[name]
    poses = _pose(ROTVECS, TRANSLATIONS)
    extra = _extra(name)
    batched = jax.jit(closed)(poses, POINTS, extra)
    single_pose = _pose(ROTVECS[-2], TRANSLATIONS[-2])
    broadcast = jax.jit(closed)(single_pose, POINTS, extra[-2])  # one camera, many points
    for k in range(len(_CASES)):
        unbatched = closed(_pose(ROTVECS[k], TRANSLATIONS[k]), POINTS[k], extra[k])
        for b, u in zip(batched, unbatched):
            np.testing.assert_allclose(b[k], u, rtol=1e-12, atol=1e-9)
    unbatched = closed(single_pose, POINTS[0], extra[-2])
    for b, u in zip(broadcast, unbatched):
        assert b.shape[0] == len(_CASES)
        np.testing.assert_allclose(b[0], u, rtol=1e-12, atol=1e-9)


def test_bearing_error_is_the_angle_and_finite_at_the_antipode():
    bearing_error = jax.jit(cameras.bearing_error)
    pose = _pose(ROTVECS[-2], TRANSLATIONS[-2])
    point = POINTS[-2]
    q = cameras.bearing(pose, point).unit_vector()
    measured = cameras.bearing(pose, point).rplus(jnp.array([0.3, -0.4]))
    error = bearing_error(pose, point, measured)
    angle = measured.distance(lieax.S2(q))
    np.testing.assert_allclose(jnp.linalg.norm(error), angle, rtol=1e-12)
    np.testing.assert_allclose(bearing_error(pose, point, q), [0.0, 0.0], atol=1e-15)
    # at (and next to) the antipode the error is still the angle, and everything is finite
    near = bearing_error(pose, point, -q)
    np.testing.assert_allclose(jnp.linalg.norm(near), np.pi, rtol=1e-12)
    identity, ahead, back = SE3.identity(), jnp.array([0.0, 0.0, 2.0]), jnp.array([0, 0, -1.0])
    error, J_pose, J_point = jax.jit(cameras.bearing_error_jacobians)(identity, ahead, back)
    np.testing.assert_allclose(jnp.linalg.norm(error), np.pi, rtol=1e-15)
    assert np.all(np.isfinite(J_pose)) and np.all(np.isfinite(J_point))
    grad = jax.jit(jax.grad(lambda X: jnp.sum(cameras.bearing_error(identity, X, back) ** 2)))(
        ahead
    )
    assert np.all(np.isfinite(grad))


def test_cal3ds2_uncalibrate_matches_autodiff_and_reduces_to_cal3_s2():
    p = jnp.array([[0.21, -0.13], [0.0, 0.0], [-0.4, 0.35]])
    pixel, J_cal, J_p = jax.jit(cameras.uncalibrate_jacobians)(CAL3DS2, p)
    auto_p = jax.vmap(jax.jacfwd(cameras.uncalibrate, 1), (None, 0))(CAL3DS2, p)
    auto_cal = jax.vmap(jax.jacfwd(cameras.uncalibrate), (None, 0))(jnp.asarray(CAL3DS2), p)
    np.testing.assert_allclose(J_p, auto_p, rtol=1e-12, atol=1e-12)
    np.testing.assert_allclose(J_cal, auto_cal, rtol=1e-12, atol=1e-12)
    no_distortion = np.concatenate([CAL3_S2, np.zeros(4)])
    np.testing.assert_allclose(
        cameras.uncalibrate(no_distortion, p), cameras.uncalibrate(CAL3_S2, p), rtol=1e-14
    )


def test_bad_inputs_are_named():
    pose = _pose(ROTVECS[0], TRANSLATIONS[0])
    with pytest.raises(
        ValueError, match=r"project: calibration must.*Cal3_S2.*Cal3DS2.*got shape \(4,\)"
    ):
        cameras.project(pose, np.ones(4), POINTS[0])
    with pytest.raises(TypeError, match="project: T_world_camera must be a lieax.SE3"):
        cameras.project(pose.rotation(), CAL3_S2, POINTS[0])
    with pytest.raises(ValueError, match="stereo_project: calibration"):
        cameras.stereo_project(pose, CAL3_S2, POINTS[0])
    with pytest.raises(ValueError, match="stereo_project_jacobians: point"):
        cameras.stereo_project_jacobians(pose, STEREO, POINTS[0, :2])
    with pytest.raises(
        ValueError, match=r"stereo_residual: measured must have shape \(\*batch, 3\)"
    ):
        cameras.stereo_residual(pose, POINTS[0], jnp.ones(2), STEREO)
    poses = fg.Var(_pose(ROTVECS[:2], TRANSLATIONS[:2]))
    points = fg.Var(POINTS[:2])
    with pytest.raises(ValueError, match="behind must be one of"):
        cameras.projection_factor(poses[[0]], points[[0]], [[1.0, 2.0]], CAL3_S2, behind="no")
    with pytest.raises(ValueError, match=r"stereo_factor: measured must have shape \(m, 3\)"):
        cameras.stereo_factor(poses[[0]], points[[0]], [[1.0, 2.0]], STEREO)
    with pytest.raises(ValueError, match=r"stereo_factor: calibration must have shape \(6,\)"):
        cameras.stereo_factor(poses[[0]], points[[0]], [[1.0, 2.0, 3.0]], CAL3_S2)


# ---- GTSAM as the oracle -------------------------------------------------------------------------


def _gtsam_pose(gtsam, rotvec, translation):
    R = Rotation.from_rotvec(np.array(rotvec)).as_matrix()
    return gtsam.Pose3(gtsam.Rot3(R), np.array(translation))


def _out(rows, cols):
    return np.zeros((rows, cols), order="F")


@pytest.mark.parametrize("calibration", ["Cal3_S2", "Cal3DS2"])
def test_pinhole_matches_gtsam(calibration):
    gtsam = pytest.importorskip("gtsam")
    K = CAL3_S2 if calibration == "Cal3_S2" else CAL3DS2
    Camera = gtsam.PinholeCameraCal3_S2 if calibration == "Cal3_S2" else gtsam.PinholeCameraCal3DS2
    Cal = gtsam.Cal3_S2 if calibration == "Cal3_S2" else gtsam.Cal3DS2
    poses = _pose(ROTVECS, TRANSLATIONS)
    pixel, J_pose, J_point, J_cal = jax.jit(cameras.project_jacobians)(poses, K, POINTS)
    for k in range(len(_CASES)):
        camera = Camera(_gtsam_pose(gtsam, ROTVECS[k], TRANSLATIONS[k]), Cal(*K))
        H_pose, H_point, H_cal = _out(2, 6), _out(2, 3), _out(2, len(K))
        expected = camera.project(np.array(POINTS[k]), H_pose, H_point, H_cal)
        np.testing.assert_allclose(pixel[k], expected, rtol=1e-12)
        np.testing.assert_allclose(
            J_pose[k], cv.se3_jacobian_from_gtsam(H_pose, rows=False), rtol=1e-9, atol=1e-9
        )
        np.testing.assert_allclose(J_point[k], H_point, rtol=1e-9, atol=1e-9)
        np.testing.assert_allclose(J_cal[k], H_cal, rtol=1e-9, atol=1e-9)


def test_cal3ds2_uncalibrate_matches_gtsam():
    gtsam = pytest.importorskip("gtsam")
    p = np.array([[0.21, -0.13], [0.0, 0.0], [-0.4, 0.35]])
    pixel, J_cal, J_p = cameras.uncalibrate_jacobians(CAL3DS2, p)
    K = gtsam.Cal3DS2(*CAL3DS2)
    for k in range(len(p)):
        H_cal, H_p = _out(2, 9), _out(2, 2)
        np.testing.assert_allclose(pixel[k], K.uncalibrate(p[k], H_cal, H_p), rtol=1e-14)
        np.testing.assert_allclose(J_cal[k], H_cal, rtol=1e-12, atol=1e-12)
        np.testing.assert_allclose(J_p[k], H_p, rtol=1e-12, atol=1e-12)


def _linearized(gtsam, factor, pose, point):
    """GTSAM's unwhitened error and Jacobians (unit noise) of a pose-point factor, the pose's
    columns in lieax's order."""
    values = gtsam.Values()
    values.insert(0, pose)
    values.insert(1, np.array(point))
    A, b = factor.linearize(values).jacobian()
    return -b, cv.se3_jacobian_from_gtsam(A[:, :6], rows=False), A[:, 6:]


def test_stereo_matches_gtsam():
    gtsam = pytest.importorskip("gtsam")
    poses = _pose(ROTVECS, TRANSLATIONS)
    measured = jnp.array([300.0, 250.0, 200.0])
    residual, (J_pose, J_point) = jax.jit(cameras.stereo_residual_jacobians)(
        poses, POINTS, measured, STEREO
    )
    K = gtsam.Cal3_S2Stereo(*STEREO)
    noise = gtsam.noiseModel.Unit.Create(3)
    factor = gtsam.GenericStereoFactor3D(gtsam.StereoPoint2(*np.asarray(measured)), noise, 0, 1, K)
    for k in range(len(_CASES)):
        pose = _gtsam_pose(gtsam, ROTVECS[k], TRANSLATIONS[k])
        projected = gtsam.StereoCamera(pose, K).project(np.array(POINTS[k])).vector()
        np.testing.assert_allclose(residual[k] + measured, projected, rtol=1e-12)
        error, H_pose, H_point = _linearized(gtsam, factor, pose, POINTS[k])
        np.testing.assert_allclose(residual[k], error, rtol=1e-9, atol=1e-9)
        np.testing.assert_allclose(J_pose[k], H_pose, rtol=1e-9, atol=1e-9)
        np.testing.assert_allclose(J_point[k], H_point, rtol=1e-9, atol=1e-9)


def test_bearing_cost_matches_gtsam():
    gtsam = pytest.importorskip("gtsam")
    poses = _pose(ROTVECS, TRANSLATIONS)
    error = jax.jit(cameras.bearing_error)(poses, POINTS, BEARINGS)
    noise = gtsam.noiseModel.Unit.Create(2)
    for k in range(len(_CASES)):
        values = gtsam.Values()
        values.insert(0, _gtsam_pose(gtsam, ROTVECS[k], TRANSLATIONS[k]))
        values.insert(1, np.array(POINTS[k]))
        factor = gtsam.BearingFactor3D(0, 1, gtsam.Unit3(np.array(BEARINGS[k])), noise)
        np.testing.assert_allclose(0.5 * np.sum(error[k] ** 2), factor.error(values), rtol=1e-10)


# ---- factors and the cheirality policy -----------------------------------------------------------


def _scene(seed=3, count=4, landmarks=12, mirrored=2):
    r"""Cameras on a line looking down $+z$ at landmarks 4-8 m ahead, pixel observations with
    0.5 px noise, initial landmarks with noise and the first `mirrored` ones mirrored through
    the first camera's centre (behind every camera)."""
    rng = np.random.default_rng(seed)
    landmarks_truth = np.column_stack(
        [rng.uniform(-2, 2, landmarks), rng.uniform(-1, 1, landmarks), rng.uniform(4, 8, landmarks)]
    )
    translations = np.column_stack([np.linspace(0, 1.5, count), np.zeros((count, 2))])
    poses = _pose(jnp.asarray(rng.normal(0, 0.05, (count, 3))), jnp.asarray(translations))
    cam, pt = (
        a.ravel() for a in np.meshgrid(np.arange(count), np.arange(landmarks), indexing="ij")
    )
    uv = np.asarray(jax.jit(cameras.project)(poses[cam], CAL3_S2, landmarks_truth[pt]))
    uv = uv + rng.normal(0, 0.5, uv.shape)
    initial = landmarks_truth + rng.normal(0, 0.1, landmarks_truth.shape)
    initial[:mirrored] = 2 * translations[0] - initial[:mirrored]
    return poses, initial, cam, pt, uv


def _graph(behind="zero"):
    poses, initial, cam, pt, uv = _scene()
    pose_var = fg.Var(poses, fixed=np.arange(poses.batch_shape[0]), name="poses")
    points = fg.Var(jnp.asarray(initial), name="points")
    factor = cameras.projection_factor(
        pose_var[cam], points[pt], uv, CAL3_S2, behind=behind, sqrt_information=2 * np.eye(2)
    )
    return fg.FactorGraph([factor]), (poses, initial, cam, pt, uv)


BEHIND_COST = 0.5 * 2 * (2 * CAL3_S2[0] * 2) ** 2  # GTSAM's residual 2 fx, whitened (σ = 0.5)


def test_count_behind_and_check_in_front():
    graph, (poses, initial, cam, pt, uv) = _graph()
    masks = cameras.behind_camera(graph)
    expected = np.isin(pt, [0, 1])
    np.testing.assert_array_equal(masks["projection_factor"], expected)
    assert cameras.count_behind(graph) == expected.sum() == 8
    with pytest.raises(
        cameras.CheiralityError, match=r"'projection_factor': 8 \(instances \[0, 1, 12"
    ):
        cameras.check_in_front(graph)
    # the "zero" policy: GTSAM's residual 2 fx and zero blocks for those observations
    residual, (J_pose, J_point) = jax.jit(cameras.projection_residual_jacobians)(
        poses[cam], jnp.asarray(initial[pt]), uv, CAL3_S2
    )
    np.testing.assert_array_equal(residual[expected], 2 * CAL3_S2[0])
    assert np.all(J_pose[expected] == 0) and np.all(J_point[expected] == 0)
    assert np.all(J_point[~expected] != 0)
    value_path = jax.jit(cameras.projection_residual)(
        poses[cam], jnp.asarray(initial[pt]), uv, CAL3_S2
    )
    np.testing.assert_allclose(value_path, residual, rtol=1e-12, atol=1e-9)
    grad = jax.grad(lambda X: jnp.sum(cameras.projection_residual(poses[cam], X, uv, CAL3_S2)))
    assert np.all(np.isfinite(jax.jit(grad)(jnp.asarray(initial[pt]))))


def test_default_policy_matches_gtsam_and_does_not_fit_the_mirror():
    """Landmarks initialized behind every camera: with the default policy they stay where they
    are (zero Jacobian), `count_behind` reports their 8 observations after the solve, and the
    cost is GTSAM's (`GenericProjectionFactorCal3_S2`, default `throwCheirality=false`) on the
    same problem to 1e-6; with `"mirror"` the solve moves them to a mirrored minimum (still behind,
    a much larger cost, reported as converged: the silent failure the default avoids)."""
    graph, (poses, initial, cam, pt, uv) = _graph()
    result = graph.solve(
        termination=Termination.gtsam(function_tolerance=1e-12, absolute_function_tolerance=1e-12)
    )
    solved = np.asarray(result.values[1])
    np.testing.assert_array_equal(solved[:2], initial[:2])
    assert cameras.count_behind(graph, result.values) == 8
    in_front_cost = float(result.cost) - 8 * BEHIND_COST
    assert 0 < in_front_cost < 2 * 40  # 40 observations in front at the noise level

    mirror_graph, _ = _graph("mirror")
    mirror = mirror_graph.solve(
        termination=Termination.gtsam(function_tolerance=1e-12, absolute_function_tolerance=1e-12)
    )
    assert cameras.count_behind(mirror_graph, mirror.values) == 8
    assert np.abs(np.asarray(mirror.values[1])[:2] - initial[:2]).max() > 0.05
    # a worse minimum, reported as converged: the silent failure
    assert mirror.status_name == "CONVERGED" and float(mirror.cost) > 10 * in_front_cost

    gtsam = pytest.importorskip("gtsam")
    noise = gtsam.noiseModel.Isotropic.Sigma(2, 0.5)
    K = gtsam.Cal3_S2(*CAL3_S2)
    factors, values = gtsam.NonlinearFactorGraph(), gtsam.Values()
    matrices = np.asarray(poses.as_matrix())
    for i, matrix in enumerate(matrices):
        values.insert(gtsam.symbol("x", i), gtsam.Pose3(matrix))
        factors.add(gtsam.NonlinearEqualityPose3(gtsam.symbol("x", i), gtsam.Pose3(matrix)))
    for j, point in enumerate(initial):
        values.insert(gtsam.symbol("l", j), np.array(point))
    for i, j, z in zip(cam, pt, uv):
        keys = gtsam.symbol("x", i), gtsam.symbol("l", j)
        factors.add(gtsam.GenericProjectionFactorCal3_S2(np.array(z), noise, *keys, K))
    params = gtsam.LevenbergMarquardtParams()
    params.setRelativeErrorTol(1e-12)
    params.setAbsoluteErrorTol(1e-12)
    gtsam_result = gtsam.LevenbergMarquardtOptimizer(factors, values, params).optimize()
    gtsam_cost = factors.error(gtsam_result)
    assert abs(float(result.cost) - gtsam_cost) < 1e-6 * gtsam_cost
    assert abs(in_front_cost - (gtsam_cost - 8 * BEHIND_COST)) < 1e-6 * in_front_cost
    for j in range(len(initial)):
        np.testing.assert_allclose(
            gtsam_result.atPoint3(gtsam.symbol("l", j)), solved[j], rtol=1e-6, atol=1e-7
        )


def test_bearing_factor_triangulates():
    """Noise-free bearings from four fixed cameras: `bearing_factor`'s solve ends at the
    landmarks (cost ~0), from starts 0.5 m off; its closed-form blocks are the residual's
    `lieax.jacobian` (the graph's linearization with and without them agree)."""
    poses, truth, cam, pt, _ = _scene(mirrored=0)  # the landmarks: its noisy initial ones
    measured = jax.jit(cameras.bearing)(poses[cam], jnp.asarray(truth[pt]))
    start = truth + np.random.default_rng(1).normal(0, 0.5, truth.shape)
    pose_var = fg.Var(poses, fixed=np.arange(poses.batch_shape[0]), name="poses")
    points = fg.Var(jnp.asarray(start), name="points")
    factor = cameras.bearing_factor(pose_var[cam], points[pt], measured)
    graph = fg.FactorGraph([factor])
    result = graph.solve(
        termination=Termination.gtsam(function_tolerance=1e-14, absolute_function_tolerance=1e-20)
    )
    assert float(result.cost) < 1e-20
    np.testing.assert_allclose(result.values[1], truth, atol=1e-8)
    kinds = (pose_var[cam], points[pt])
    autodiff = fg.FactorGraph([fg.Factor(cameras.bearing_error, kinds, measured.unit_vector())])
    for closed, auto in zip(graph.linearize(), autodiff.linearize()):
        for a, b in zip(jax.tree_util.tree_leaves(closed), jax.tree_util.tree_leaves(auto)):
            np.testing.assert_allclose(a, b, rtol=1e-9, atol=1e-9)


def test_bearing_series_branch():
    """Below 1e-2 rad (the series of θ / sin θ) and at θ = 0 the closed-form blocks equal
    `lieax.jacobian` of the error and central differences along the point."""
    pose, point = _pose(ROTVECS[-2], TRANSLATIONS[-2]), POINTS[-2]
    q = cameras.bearing(pose, point)
    measured = jnp.stack([q.rplus(jnp.array([3e-4, -4e-4])).unit_vector(), q.unit_vector()])

    @jax.jit
    def blocks(m):
        _, J_pose, J_point = cameras.bearing_error_jacobians(pose, point, m)
        auto = lieax.jacobian(cameras.bearing_error, (0, 1))(pose, point, m)
        columns = jax.vmap(
            lambda d: (
                cameras.bearing_error(pose, point + d, m)
                - cameras.bearing_error(pose, point - d, m)
            )
        )(STEP * jnp.eye(3))
        return (
            jnp.concatenate([J_pose, J_point], -1),
            jnp.concatenate(auto, -1),
            columns.T / (2 * STEP),
        )

    for m in measured:
        closed, auto, differences = blocks(m)
        assert _relative(auto, closed) < 1e-12
        assert _relative(closed[:, 6:], differences) < 1e-8
