"""Bundle-adjustment building blocks: Snavely's reprojection factor and its closed-form Jacobians
(against `lieax.jacobian` of the residual in both modes and central differences in local
coordinates, float64, over rotation regimes, batched and unbatched), the BAL camera converters,
BAL file round trips and malformed-file errors, and the synthetic problem generator."""

import bz2
import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.spatial.transform import Rotation

import lieax
from lieax import ba

# rotation vectors of the regimes: identity, 1e-9 from it, ~1e-4 rad, near π, random
_AXIS = np.array([0.3, -0.5, 0.8]) / np.linalg.norm([0.3, -0.5, 0.8])
_RANDOM = np.array([0.7, -1.9, 0.4])
REGIMES = {
    "identity": np.zeros(3),
    "near-identity-1e-9": 1e-9 * _AXIS,
    "small-1e-4": 1e-4 * _AXIS,
    "near-pi-1e-4": (np.pi - 1e-4) * _AXIS,
    "near-pi-1e-6": (np.pi - 1e-6) * _AXIS,
    "random": _RANDOM,
}
INTRINSICS = np.array([480.0, 0.07, -0.03])


def _case(rotvec, seed, pure_translation=False):
    r"""A camera, point and observation with $P = (a, b, -4)$, $|a|, |b| \le 1$ (in front)."""
    rng = np.random.default_rng(seed)
    point = rng.uniform(-2, 2, 3)
    R = Rotation.from_rotvec(rotvec).as_matrix()
    P = np.array([*rng.uniform(-1, 1, 2), -4.0])
    t = P - (0 if pure_translation else R @ point)
    if pure_translation:
        point = np.zeros(3)
    pose = lieax.SE3.from_rotation_and_translation(lieax.SO3.exp(jnp.asarray(rotvec)), t)
    observation = rng.uniform(-100, 100, 2)
    return pose, jnp.asarray(INTRINSICS), jnp.asarray(point), jnp.asarray(observation)


CASE_NAMES = [*REGIMES, "pure-translation"]


@functools.cache
def cases():
    """`{name: (pose, intrinsics, point, observation)}` of every regime (built when a test first
    needs them, not while pytest collects the file)."""
    built = {name: _case(rotvec, seed) for seed, (name, rotvec) in enumerate(REGIMES.items())}
    built["pure-translation"] = _case(np.zeros(3), 10, pure_translation=True)
    return built


closed_form = jax.jit(ba.reprojection_jacobians)
autodiff = {
    mode: jax.jit(lieax.jacobian(ba.reprojection_residual, (0, 1, 2), mode=mode))
    for mode in ("fwd", "rev")
}


@jax.jit
def central_differences(pose, intrinsics, point, observation, step=1e-6):
    """The 2×12 Jacobian by central differences in local coordinates (pose ⊕ δ, then +)."""

    def moved(delta):
        return ba.reprojection_residual(
            pose.rplus(delta[:6]), intrinsics + delta[6:9], point + delta[9:], observation
        )

    basis = step * jnp.eye(12)  # ± in one vmap: one copy of the residual's program
    plus, minus = jnp.split(jax.vmap(moved)(jnp.concatenate([basis, -basis])), 2)
    return ((plus - minus) / (2 * step)).T


def _stacked(J_pose, J_intrinsics, J_point):
    return np.concatenate([J_pose, J_intrinsics, J_point], axis=-1)


def _relative_error(a, b):
    return np.max(np.abs(np.asarray(a) - np.asarray(b))) / np.max(np.abs(np.asarray(b)))


@pytest.mark.parametrize("name", CASE_NAMES)
def test_closed_form_matches_autodiff_and_differences(name):
    pose, intrinsics, point, observation = cases()[name]
    residual, *blocks = closed_form(pose, intrinsics, point, observation)
    J = _stacked(*blocks)
    assert J.shape == (2, 12) and np.all(np.isfinite(J))
    np.testing.assert_allclose(
        residual, ba.reprojection_residual(pose, intrinsics, point, observation), rtol=1e-12
    )
    for mode, jacobian in autodiff.items():
        J_auto = _stacked(*jacobian(pose, intrinsics, point, observation))
        assert _relative_error(J_auto, J) < 1e-10, mode
    J_fd = central_differences(pose, intrinsics, point, observation)
    assert _relative_error(J, J_fd) < 1e-8


@pytest.mark.parametrize("name", ["identity", "near-pi-1e-6", "random"])
def test_gradients_are_finite(name):
    pose, intrinsics, point, observation = cases()[name]

    def cost(pose, intrinsics, point):
        r = ba.reprojection_residual(pose, intrinsics, point, observation)
        return 0.5 * jnp.sum(r * r)

    grads = lieax.grad(cost, (0, 1, 2))(pose, intrinsics, point)
    residual, J_pose, J_intrinsics, J_point = closed_form(pose, intrinsics, point, observation)
    for g, J in zip(grads, (J_pose, J_intrinsics, J_point)):
        assert np.all(np.isfinite(g))
        np.testing.assert_allclose(g, residual @ J, rtol=1e-9, atol=1e-9 * np.abs(J).max())


def _batch():
    names = CASE_NAMES
    pose = lieax.SE3(jnp.stack([cases()[n][0].parameters() for n in names]))
    rest = [jnp.stack([cases()[n][i] for n in names]) for i in (1, 2, 3)]
    return names, pose, *rest


def test_batched_and_vmapped_match_unbatched():
    names, pose, intrinsics, point, observation = _batch()
    batched = closed_form(pose, intrinsics, point, observation)
    vmapped = jax.vmap(ba.reprojection_jacobians)(pose, intrinsics, point, observation)
    auto = {m: jax.vmap(j)(pose, intrinsics, point, observation) for m, j in autodiff.items()}
    for k, name in enumerate(names):
        single = closed_form(*cases()[name])
        for b, v, s in zip(batched, vmapped, single):
            np.testing.assert_allclose(b[k], s, rtol=1e-12, atol=1e-12)
            np.testing.assert_allclose(v[k], s, rtol=1e-12, atol=1e-12)
        for blocks in auto.values():
            np.testing.assert_allclose(
                _stacked(*(a[k] for a in blocks)), _stacked(*single[1:]), rtol=1e-9, atol=1e-9
            )


def test_one_camera_broadcasts_over_points():
    _, _, _, point, observation = _batch()
    pose, intrinsics, _, _ = cases()["random"]
    residual, J_pose, J_intrinsics, J_point = closed_form(pose, intrinsics, point, observation)
    assert residual.shape == (len(point), 2) and J_pose.shape == (len(point), 2, 6)
    assert J_intrinsics.shape == J_point.shape == (len(point), 2, 3)
    for k in range(len(point)):
        single = closed_form(pose, intrinsics, point[k], observation[k])
        np.testing.assert_allclose(J_pose[k], single[1], rtol=1e-12, atol=1e-12)


def test_points_behind_the_camera_stay_finite():
    """Like Ceres, nothing special for $P_z > 0$: finite values and correct Jacobians."""
    pose, intrinsics, point, observation = cases()["random"]
    behind = pose.inverse() @ jnp.array([0.3, -0.2, 2.0])
    residual, *blocks = closed_form(pose, intrinsics, behind, observation)
    assert np.all(np.isfinite(residual)) and all(np.all(np.isfinite(b)) for b in blocks)
    J_fd = central_differences(pose, intrinsics, behind, observation)
    assert _relative_error(_stacked(*blocks), J_fd) < 1e-8


def test_bal_camera_converters_match_scipy():
    rng = np.random.default_rng(3)
    rotvecs = np.concatenate([np.stack(list(REGIMES.values())), Rotation.random(20, 4).as_rotvec()])
    cameras = np.concatenate(
        [rotvecs, rng.normal(size=(len(rotvecs), 3)), np.tile(INTRINSICS, (len(rotvecs), 1))], 1
    )
    pose, intrinsics = ba.bal_to_camera(jnp.asarray(cameras))
    assert isinstance(pose, lieax.SE3) and pose.batch_shape == (len(cameras),)
    np.testing.assert_allclose(
        pose.rotation().as_matrix(), Rotation.from_rotvec(rotvecs).as_matrix(), atol=1e-14
    )
    np.testing.assert_allclose(pose.translation(), cameras[:, 3:6], rtol=1e-15)
    np.testing.assert_array_equal(intrinsics, cameras[:, 6:])
    back = ba.camera_to_bal(pose, intrinsics)
    np.testing.assert_allclose(back, cameras, atol=1e-12)
    # writable NumPy, as SciPy takes it (a read-only view was refused: issue 32)
    assert isinstance(back, np.ndarray) and back.flags.writeable
    np.testing.assert_allclose(
        Rotation.from_rotvec(back[:, :3]).as_matrix(), pose.rotation().as_matrix(), atol=1e-14
    )
    # the lieax projection and the generator's NumPy one agree
    points = rng.normal(size=(len(cameras), 3)) + np.array([0.0, 0.0, -5.0])
    u, _ = ba.project_numpy(cameras, points)
    np.testing.assert_allclose(ba.project(pose, intrinsics, jnp.asarray(points)), u, rtol=1e-12)


def test_bad_inputs_are_named():
    pose, intrinsics, point, observation = cases()["random"]
    with pytest.raises(TypeError, match="SE3"):
        ba.reprojection_residual(pose.rotation(), intrinsics, point, observation)
    with pytest.raises(ValueError, match="intrinsics"):
        ba.reprojection_jacobians(pose, intrinsics[:2], point, observation)
    with pytest.raises(ValueError, match="observation"):
        ba.reprojection_residual(pose, intrinsics, point, jnp.zeros(3))
    with pytest.raises(ValueError, match="do not broadcast"):
        ba.reprojection_residual(pose, intrinsics, jnp.zeros((4, 3)), jnp.zeros((5, 2)))
    with pytest.raises(TypeError, match="floating"):
        ba.reprojection_residual(pose, intrinsics, jnp.zeros(3, dtype=jnp.int32), observation)
    with pytest.raises(ValueError, match="BAL cameras"):
        ba.bal_to_camera(jnp.zeros((3, 8)))


# --- BAL files ---------------------------------------------------------------------------


@pytest.fixture(scope="module")
def small():
    return ba.synthetic_bal(6, 50, 180, noise=0.5, outlier_fraction=0.1, seed=1)


@pytest.mark.parametrize("suffix", [".txt", ".txt.bz2"])
def test_bal_round_trip(small, tmp_path, suffix):
    path = tmp_path / f"problem-6-50{suffix}"
    ba.write_bal(path, small.problem)
    if suffix.endswith(".bz2"):
        assert path.read_bytes()[:3] == b"BZh"
    read = ba.read_bal(path)
    assert (read.num_cameras, read.num_points, read.num_observations) == (6, 50, 180)
    np.testing.assert_array_equal(read.camera_indices, small.problem.camera_indices)
    np.testing.assert_array_equal(read.point_indices, small.problem.point_indices)
    for field in ("observations", "cameras", "points"):
        np.testing.assert_allclose(
            getattr(read, field), getattr(small.problem, field), rtol=1e-12, atol=0
        )
    pose, intrinsics = read.camera_variables()
    np.testing.assert_allclose(ba.camera_to_bal(pose, intrinsics), read.cameras, atol=1e-12)


def _bal_text(camera_lines=None):
    """A valid 2-camera, 2-point, 4-observation file: header line 1, observations 2-5, camera
    values 6-23 (one per line), point values 24-29."""
    lines = ["2 2 4", "0 0 1.5 -2.5", "1 0 3.0 4.0", "0 1 -1.0 2.0", "1 1 0.5 0.25"]
    cameras = [f"{v:.6e}" for v in (0.1, 0.2, 0.3, 0, 0, -5, 500, 0.01, 0.001) * 2]
    lines += cameras if camera_lines is None else camera_lines
    lines += ["0.1", "0.2", "0.3", "-0.1", "-0.2", "-0.3"]
    return lines


def test_bal_reads_several_values_per_line(tmp_path):
    lines = _bal_text()
    grouped = lines[:5] + [" ".join(lines[5:14]), " ".join(lines[14:23])] + lines[23:]
    path = tmp_path / "grouped.txt"
    path.write_text("\n".join(grouped) + "\n\n")
    expected = tmp_path / "plain.txt"
    expected.write_text("\n".join(lines))
    a, b = ba.read_bal(path), ba.read_bal(expected)
    np.testing.assert_array_equal(a.cameras, b.cameras)
    np.testing.assert_array_equal(a.points, b.points)
    assert a.cameras[1, 6] == 500 and a.points[1, 2] == -0.3


def _edit(line, text):
    lines = _bal_text()
    lines[line - 1] = text
    return lines


MALFORMED = {
    "short-header": (["2 2"] + _bal_text()[1:], 1, "header"),
    "non-integer-header": (_edit(1, "2 x 4"), 1, "header"),
    "observation-fields": (_edit(3, "1 0 3.0"), 3, "4 fields"),
    "observation-not-a-number": (_edit(4, "0 1 abc 2.0"), 4, "'abc' is not a number"),
    "camera-out-of-range": (_edit(5, "2 1 0.5 0.25"), 5, "camera index '2'"),
    "point-not-integer": (_edit(2, "0 0.5 1.5 -2.5"), 2, "point index '0.5'"),
    "negative-index": (_edit(2, "-1 0 1.5 -2.5"), 2, "camera index '-1'"),
    "nan-observation": (_edit(3, "1 0 nan 4.0"), 3, "non-finite"),
    "nan-camera": (_edit(12, "nan"), 12, "non-finite value 'nan'"),
    "inf-point": (_edit(27, "inf"), 27, "non-finite"),
    "camera-not-a-number": (_edit(20, "1.0e"), 20, "'1.0e' is not a number"),
    "truncated-values": (_bal_text()[:-2], 27, "ends after 22 of the 24"),
    "truncated-observations": (_bal_text()[:3], 3, "ends after 2 of 4 observation"),
    "extra-values": (_bal_text() + ["1.0"], 30, "values after the 24"),
}


@pytest.mark.parametrize("name", list(MALFORMED))
def test_malformed_bal_names_file_and_line(tmp_path, name):
    lines, line, message = MALFORMED[name]
    path = tmp_path / "problem.txt"
    path.write_text("\n".join(lines) + "\n")
    with pytest.raises(ba.BALError, match=message) as error:
        ba.read_bal(path)
    assert f"{path}:{line}:" in str(error.value)


def test_malformed_bz2_and_empty(tmp_path):
    path = tmp_path / "problem.txt.bz2"
    with bz2.open(path, "wt") as handle:
        handle.write("\n".join(_edit(12, "nan")))
    with pytest.raises(ba.BALError, match=f"{path}:12:"):
        ba.read_bal(path)
    broken = tmp_path / "broken.txt.bz2"
    broken.write_bytes(b"BZh9 not really bz2")
    with pytest.raises(ba.BALError, match="cannot be read"):
        ba.read_bal(broken)
    empty = tmp_path / "empty.txt"
    empty.write_text("\n\n")
    with pytest.raises(ba.BALError, match="empty"):
        ba.read_bal(empty)
    with pytest.raises(FileNotFoundError):
        ba.read_bal(tmp_path / "missing.txt")


def test_write_bal_rejects_bad_problems(small, tmp_path):
    bad = dataclasses.replace(small.problem, point_indices=small.problem.point_indices + 50)
    with pytest.raises(ValueError, match="point indices"):
        ba.write_bal(tmp_path / "bad.txt", bad)
    with pytest.raises(ValueError, match="shapes"):
        small.problem.with_parameters(small.problem.cameras[:, :6], small.problem.points)


# --- synthetic problems ------------------------------------------------------------------


@pytest.fixture(scope="module")
def ladybug():
    return ba.synthetic_bal(
        *ba.SYNTHETIC_PRESETS["ladybug-49"], noise=1.0, outlier_fraction=0.02, seed=0
    )


@jax.jit
def _residuals(cameras, points, camera_indices, point_indices, observations):
    pose, intrinsics = ba.bal_to_camera(cameras)
    return jax.vmap(ba.reprojection_residual)(
        pose[camera_indices], intrinsics[camera_indices], points[point_indices], observations
    )


def test_synthetic_invariants(ladybug):
    problem, truth, outliers = ladybug
    n, m, k = ba.SYNTHETIC_PRESETS["ladybug-49"]
    assert (problem.num_cameras, problem.num_points, problem.num_observations) == (n, m, k)
    np.testing.assert_array_equal(problem.observations, truth.observations)
    per_point = np.bincount(problem.point_indices, minlength=m)
    per_camera = np.bincount(problem.camera_indices, minlength=n)
    assert per_point.min() >= 2 and per_point.max() <= n
    assert per_camera.min() >= 0.3 * k / n
    pairs = problem.camera_indices * m + problem.point_indices
    assert len(np.unique(pairs)) == k  # no camera sees a point twice
    for state in (truth, problem):
        _, depth = ba.project_numpy(
            state.cameras[state.camera_indices], state.points[state.point_indices]
        )
        assert depth.max() < -2.0  # every observed point is in front of its camera
    assert outliers.sum() == round(0.02 * k)


def test_true_parameters_give_residuals_at_the_noise_level(ladybug):
    problem, truth, outliers = ladybug
    arrays = (truth.camera_indices, truth.point_indices, truth.observations)
    residual = np.asarray(_residuals(jnp.asarray(truth.cameras), truth.points, *arrays))
    inliers = residual[~outliers]
    assert 0.97 < np.std(inliers) < 1.03 and abs(np.mean(inliers)) < 0.03
    assert np.median(np.linalg.norm(residual[outliers], axis=1)) > 30
    start = np.asarray(_residuals(jnp.asarray(problem.cameras), problem.points, *arrays))
    assert np.sqrt(np.mean(start[~outliers] ** 2)) > 3  # the start is visibly perturbed
    u, _ = ba.project_numpy(truth.cameras[truth.camera_indices], truth.points[truth.point_indices])
    np.testing.assert_allclose(residual, u - truth.observations, rtol=1e-9, atol=1e-9)


def test_synthetic_is_seeded_and_checks_its_arguments():
    a, b = ba.synthetic_bal(4, 30, 80, seed=5), ba.synthetic_bal(4, 30, 80, seed=5)
    np.testing.assert_array_equal(a.problem.cameras, b.problem.cameras)
    np.testing.assert_array_equal(a.problem.observations, b.problem.observations)
    c = ba.synthetic_bal(4, 30, 80, seed=6)
    assert not np.allclose(a.truth.points, c.truth.points)
    exact = ba.synthetic_bal(4, 30, 120, noise=0.0)  # every point seen by all 4 cameras
    assert np.all(np.bincount(exact.truth.point_indices) == 4)
    truth = exact.truth
    u, _ = ba.project_numpy(truth.cameras[truth.camera_indices], truth.points[truth.point_indices])
    np.testing.assert_array_equal(u, truth.observations)
    for kwargs, message in (
        (dict(num_observations=59), r"\[60, 120\]"),
        (dict(num_observations=121), r"\[60, 120\]"),
        (dict(num_cameras=1), "num_cameras"),
        (dict(outlier_fraction=1.0), "outlier_fraction"),
        (dict(noise=-1.0), "noise"),
        (dict(point_noise=float("nan")), "point_noise"),
        (dict(focal_length=0.0), "focal_length"),
    ):
        arguments = dict(num_cameras=4, num_points=30, num_observations=80) | kwargs
        with pytest.raises(ValueError, match=message):
            ba.synthetic_bal(**arguments)


def test_gtsam_reads_our_files_and_projects_alike(small, tmp_path):
    """An independent implementation of the format and the camera: GTSAM's `readBal` (which
    flips BAL's $-z$-looking camera and the image $v$ axis) reads what `write_bal` wrote, and
    its `PinholeCamera<Cal3Bundler>` projects every point where `lieax.ba.project` does."""
    gtsam = pytest.importorskip("gtsam")
    path = tmp_path / "problem.txt"
    ba.write_bal(path, small.problem)
    data = gtsam.readBal(str(path))
    assert (data.numberCameras(), data.numberTracks()) == (6, 50)
    problem = small.problem
    pose, intrinsics = problem.camera_variables()
    cameras, points = problem.camera_indices, problem.points[problem.point_indices]
    ours = np.asarray(ba.project(pose[cameras], intrinsics[cameras], jnp.asarray(points)))
    for j in range(problem.num_points):
        track = data.track(j)
        (rows,) = np.nonzero(problem.point_indices == j)
        assert track.numberMeasurements() == len(rows)
        np.testing.assert_allclose(track.point3(), problem.points[j], rtol=1e-6)  # read as float
        for k, row in enumerate(rows):
            camera, measured = track.measurement(k)
            assert camera == problem.camera_indices[row]
            np.testing.assert_allclose(measured * [1, -1], problem.observations[row], rtol=1e-6)
            theirs = data.camera(camera).project(track.point3())
            np.testing.assert_allclose(theirs * [1, -1], ours[row], rtol=1e-5, atol=1e-4)


def test_camera_as_one_variable():
    """The `(pose, intrinsics)` camera variable: its 2×9 block is the pose block then the
    intrinsics block, as `lieax.jacobian` orders the pytree's tangent."""
    pose, intrinsics, point, observation = cases()["random"]
    camera = (pose, intrinsics)
    residual, (J_camera, J_point) = ba.camera_jacobians(camera, point, observation)
    _, J_pose, J_intrinsics, J_point_expected = closed_form(pose, intrinsics, point, observation)
    np.testing.assert_allclose(J_camera, np.concatenate([J_pose, J_intrinsics], -1), rtol=1e-12)
    np.testing.assert_allclose(J_point, J_point_expected, rtol=1e-12)
    J_auto_camera, J_auto_point = lieax.jacobian(ba.camera_residual, (0, 1))(
        camera, point, observation
    )
    assert lieax.tangent_dim(camera) == 9
    np.testing.assert_allclose(np.concatenate(J_auto_camera, -1), J_camera, rtol=1e-10)
    np.testing.assert_allclose(J_auto_point, J_point, rtol=1e-10)
    np.testing.assert_allclose(ba.camera_residual(camera, point, observation), residual)
