"""Bundler `.out` files (`read_bundler` / `write_bundler`): the camera convention against a scene
projected by hand, round trips, GTSAM's `SfmData.FromBundlerFile` as an oracle, malformed lines."""

import numpy as np
import pytest
from scipy.spatial.transform import Rotation

from lieax.ba import (
    BALError,
    BALProblem,
    BundlerProblem,
    project_numpy,
    read_bundler,
    synthetic_bal,
    write_bundler,
)


def _scene(seed=0):
    """Three cameras around the origin looking at it (down their -z axes), six points, every point
    seen by two or three cameras; observations exact."""
    rng = np.random.default_rng(seed)
    rotvecs = np.array([[0.1, -0.2, 0.05], [0.3, 0.9, -0.1], [-0.2, -1.1, 0.2]])
    R = Rotation.from_rotvec(rotvecs).as_matrix()
    t = np.array([[0.1, -0.2, -6.0], [0.3, 0.1, -5.5], [-0.2, 0.2, -6.5]])
    intrinsics = np.array([[500.0, -0.1, 0.02], [520.0, 0.05, -0.01], [480.0, 0.0, 0.0]])
    points = rng.uniform(-1, 1, (6, 3))
    views = [(p, c) for p in range(6) for c in range(3) if (p + c) % 4 != 3]
    point_indices = np.array([p for p, _ in views])
    camera_indices = np.array([c for _, c in views])
    cameras = np.concatenate([rotvecs, t, intrinsics], axis=1)
    observed, depth = project_numpy(cameras[camera_indices], points[point_indices])
    assert np.all(depth < 0)  # in front of the cameras
    colors = rng.integers(0, 256, (6, 3))
    keys = rng.integers(0, 5000, len(views))
    lines = ["# Bundle file v0.3", "3 6"]
    for c in range(3):
        lines += [" ".join(f"{v:.17g}" for v in row) for row in (intrinsics[c], *R[c], t[c])]
    for p in range(6):
        mine = np.flatnonzero(point_indices == p)
        lines += [" ".join(f"{v:.17g}" for v in points[p]), " ".join(map(str, colors[p]))]
        lines.append(
            f"{len(mine)} "
            + " ".join(f"{camera_indices[k]} {keys[k]} {observed[k, 0]:.17g} {observed[k, 1]:.17g}" for k in mine)
        )  # fmt: skip
    truth = BundlerProblem(camera_indices, point_indices, observed, cameras, points, colors, keys)
    return "\n".join(lines) + "\n", truth


def test_reads_bundler_cameras_as_bal_cameras(tmp_path):
    text, truth = _scene()
    path = tmp_path / "scene.out"
    path.write_text(text)
    problem = read_bundler(path)
    assert isinstance(problem, BALProblem)
    np.testing.assert_allclose(problem.cameras, truth.cameras, rtol=0, atol=1e-14)
    np.testing.assert_array_equal(problem.points, truth.points)
    np.testing.assert_array_equal(problem.observations, truth.observations)
    np.testing.assert_array_equal(problem.camera_indices, truth.camera_indices)
    np.testing.assert_array_equal(problem.point_indices, truth.point_indices)
    np.testing.assert_array_equal(problem.colors, truth.colors)
    np.testing.assert_array_equal(problem.keypoint_indices, truth.keypoint_indices)
    # Snavely's projection of the converted cameras reproduces the file's pixels
    projected, _ = project_numpy(
        problem.cameras[problem.camera_indices], problem.points[problem.point_indices]
    )
    np.testing.assert_allclose(projected, problem.observations, rtol=0, atol=1e-9)


def test_round_trips(tmp_path):
    text, _ = _scene(1)
    (tmp_path / "a.out").write_text(text)
    problem = read_bundler(tmp_path / "a.out")
    write_bundler(tmp_path / "b.out", problem)
    again = read_bundler(tmp_path / "b.out")
    np.testing.assert_allclose(again.cameras, problem.cameras, rtol=0, atol=1e-15)
    for name in ("points", "observations", "camera_indices", "point_indices", "colors"):
        np.testing.assert_array_equal(getattr(again, name), getattr(problem, name))
    np.testing.assert_array_equal(again.keypoint_indices, problem.keypoint_indices)
    # a BAL problem (observations camera by camera) comes back grouped by point, white, key 0
    bal = synthetic_bal(4, 10, 30, seed=2).problem
    write_bundler(tmp_path / "c.out", bal)
    back = read_bundler(tmp_path / "c.out")
    order = np.argsort(bal.point_indices, kind="stable")
    np.testing.assert_array_equal(back.point_indices, bal.point_indices[order])
    np.testing.assert_array_equal(back.camera_indices, bal.camera_indices[order])
    np.testing.assert_array_equal(back.observations, bal.observations[order])
    np.testing.assert_allclose(back.cameras, bal.cameras, rtol=0, atol=1e-14)
    assert np.all(back.colors == 255) and np.all(back.keypoint_indices == 0)


def test_gtsam_reads_the_same_cameras(tmp_path):
    gtsam = pytest.importorskip("gtsam")
    text, truth = _scene(3)
    path = tmp_path / "scene.out"
    path.write_text(text)
    problem = read_bundler(path)
    data = gtsam.SfmData.FromBundlerFile(str(path))
    assert data.numberCameras() == problem.num_cameras
    k = 0
    for p in range(data.numberTracks()):
        track = data.track(p)
        # GTSAM reads the numbers as float (single precision)
        np.testing.assert_allclose(track.point3(), problem.points[p], rtol=1e-6)
        for m in range(track.numberMeasurements()):
            camera, measured = track.measurement(m)
            assert camera == problem.camera_indices[k] and problem.point_indices[k] == p
            x, y = problem.observations[k]
            np.testing.assert_allclose(measured, [x, -y], rtol=1e-6)  # GTSAM's pixels: y down
            projected = data.camera(camera).project(track.point3())
            np.testing.assert_allclose(projected, [x, -y], rtol=1e-5, atol=1e-4)
            k += 1
    assert k == problem.num_observations


@pytest.mark.parametrize(
    "edit, line, message",
    [
        (lambda s: s.replace("# Bundle file v0.3", "# Bundle v1"), 1, "expected the header"),
        (lambda s: s.replace("3 6\n", "3 x\n"), 2, "expected an integer, got 'x'"),
        (lambda s: s.replace("3 6\n", "3 7\n"), 35, "the file ends before point 6's position"),
        (lambda s: s.replace("3 6\n", "2 6\n"), 14, "expected an integer, got '"),
        (lambda s: _line(s, 4, "1 0 0"), 4, "camera 0's R is not a rotation"),
        (
            lambda s: _line(_line(_line(s, 4, "0 0 0"), 5, "0 0 0"), 6, "0 0 0"),
            4,
            "camera 0 is all",
        ),
        (lambda s: _line(s, 3, "500 nan 0"), 3, "non-finite value in camera 0"),
        (lambda s: _line(s, 19, "0 0 256"), 19, r"colour \[0, 0, 256\] outside 0-255"),
        (lambda s: _line(s, 20, "2 0 3 2.0 1.0"), 20, r".*\(9 fields\), got 5"),
        (lambda s: _line(s, 20, "1 3 3 2.0 1.0"), 20, "view 0 has camera 3 .of 3."),
        (lambda s: _line(s, 20, "1 0 3 2.0 y"), 20, "expected a number, got 'y'"),
        (lambda s: s + "1 2 3\n", 36, "lines after the last point"),
    ],
)
def test_malformed_files_name_file_and_line(tmp_path, edit, line, message):
    text, _ = _scene()
    path = tmp_path / "bad.out"
    path.write_text(edit(text))
    with pytest.raises(BALError, match=rf"bad\.out:{line}: {message}"):
        read_bundler(path)


def _line(text, number, replacement):
    lines = text.split("\n")
    lines[number - 1] = replacement
    return "\n".join(lines)
