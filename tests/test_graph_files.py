"""TORO and GTSAM text datasets (`read_toro`): the files GTSAM's `load2D` / `load3D` read, with
landmarks and bearing-range sightings; checked by hand and against GTSAM's own loader."""

import math

import numpy as np
import pytest

from lieax.graph import (
    LandmarkGraph,
    PoseGraph,
    ToroError,
    ToroWarning,
    cost,
    optimize,
    read_g2o,
    read_toro,
    to_factor_graph,
    write_g2o,
)

# victoria_park.txt's layout: poses and landmarks share one counter (ids not contiguous), pose 5
# and landmark 5 are different variables, and pose 9 is first seen in a sighting.
LANDMARK_FILE = """\
ODOMETRY 0 1 0.5 0.01 0.02 0.0001 0 0 4e-06 0 4e-06
ODOMETRY 1 2 0.6 -0.02 0.1 0.0001 0 0 4e-06 0 4e-06
LANDMARK 2 5 11.5 -3.2 0.4 0 0.4
ODOMETRY 2 5 0.7 0.03 -0.05 0.0001 0 0 4e-06 0 4e-06
BR 5 3 0.3 4.0 0.05 0.2
LANDMARK 5 7 2.0 1.0 0.4 0 0.9
ODOMETRY 5 8 0.4 0.0 0.3 0.0001 0 0 4e-06 0 4e-06
LANDMARK 8 5 10.9 -3.0 0.4 0 0.4
BR 9 3 -2.9 3.0 0.1 0.3
ODOMETRY 8 9 0.2 0.1 -0.2 0.0001 0 0 4e-06 0 4e-06
"""

# TORO (w10000.graph's layout: `a 0 b c 0 0`, covariances in TORO order) and g2o-layout lines
# mixed, vertices that disagree with the edges (a non-zero cost), ids not starting at 0.
TORO_FILE = """\
VERTEX2 10 0 0 0
VERTEX2 12 1.1 0.1 0.05
VERTEX2 13 2.0 0.3 0.4
VERTEX2 17 2.2 1.4 1.7
EDGE2 10 12 1.0 0.0 0.0 0.5 0 0.25 0.04 0 0
EDGE2 12 13 1.0 0.2 0.3 2.0 0 0.5 0.1 0 0
EDGE2 13 17 0.5 1.0 1.2 1 0 0 4 0 0.09
EDGE2 17 10 -1.0 2.0 -1.6 0.3 0 0 0.2 0 0.01
"""


def _write(tmp_path, text, name="data.txt"):
    path = tmp_path / name
    path.write_text(text)
    return path


def _compose(a, b):
    """(x, y, θ) poses composed."""
    c, s = math.cos(a[2]), math.sin(a[2])
    return (a[0] + c * b[0] - s * b[1], a[1] + s * b[0] + c * b[1], a[2] + b[2])


def _xytheta(poses):
    p = np.asarray(poses.parameters())
    return np.stack([p[:, 2], p[:, 3], np.arctan2(p[:, 1], p[:, 0])], axis=1)


def _sightings_cost(graph):
    """½‖R r‖² of the bearing-range sightings, r = (wrapped bearing error, range error)."""
    br = graph.bearing_range
    pose = np.asarray(graph.poses.parameters())[br.pose]
    delta = np.asarray(graph.landmarks)[br.landmark] - pose[:, 2:]
    c, s = pose[:, 0], pose[:, 1]
    x, y = c * delta[:, 0] + s * delta[:, 1], -s * delta[:, 0] + c * delta[:, 1]
    bearing = np.angle(np.exp(1j * (np.arctan2(y, x) - np.asarray(br.bearing))))
    residual = np.stack([bearing, np.hypot(x, y) - np.asarray(br.range)], axis=1)
    whitened = np.einsum("kij,kj->ki", np.asarray(br.sqrt_information), residual)
    return 0.5 * float(np.sum(whitened**2))


def test_landmark_file_ids_values_and_noise(tmp_path):
    graph = read_toro(_write(tmp_path, LANDMARK_FILE))
    assert isinstance(graph, LandmarkGraph)
    np.testing.assert_array_equal(graph.vertex_ids, [0, 1, 2, 5, 8, 9])
    np.testing.assert_array_equal(graph.landmark_ids, [3, 5, 7])
    # initial values as load2D makes them: dead reckoning from the identity in file order; pose 9
    # first seen in a sighting starts at the identity (its odometry comes later)
    x0 = (0.0, 0.0, 0.0)
    x1 = _compose(x0, (0.5, 0.01, 0.02))
    x2 = _compose(x1, (0.6, -0.02, 0.1))
    x5 = _compose(x2, (0.7, 0.03, -0.05))
    x8 = _compose(x5, (0.4, 0.0, 0.3))
    np.testing.assert_allclose(
        _xytheta(graph.poses), [x0, x1, x2, x5, x8, (0, 0, 0)], rtol=0, atol=1e-14
    )

    def sighted(pose, b, r):
        return _compose(pose, (r * math.cos(b), r * math.sin(b), 0))[:2]

    expected = [
        sighted(x5, 0.3, 4.0),
        sighted(x2, math.atan2(-3.2, 11.5), math.hypot(11.5, -3.2)),
        sighted(x5, math.atan2(1.0, 2.0), math.hypot(2.0, 1.0)),
    ]
    np.testing.assert_allclose(graph.landmarks, expected, rtol=0, atol=1e-13)
    # odometry noise `a 0 0 b 0 c`: g2o order, covariances
    np.testing.assert_allclose(
        graph.information, np.broadcast_to(np.diag([1e4, 2.5e5, 2.5e5]), (5, 3, 3)), rtol=1e-12
    )
    br = graph.bearing_range
    np.testing.assert_array_equal(br.pose, [2, 3, 3, 4, 5])
    np.testing.assert_array_equal(br.landmark, [1, 0, 2, 1, 0])
    np.testing.assert_allclose(np.asarray(br.bearing)[[1, 4]], [0.3, -2.9])
    np.testing.assert_allclose(br.range[0], math.hypot(11.5, -3.2))
    # LANDMARK sigmas: sqrt(v1 / 10), sqrt(v1) when v1 == v3, else 1 and 1
    sigmas = 1 / np.diagonal(np.asarray(br.sqrt_information), axis1=1, axis2=2)
    np.testing.assert_allclose(
        sigmas,
        [[math.sqrt(0.04), math.sqrt(0.4)], [0.05, 0.2], [1, 1], [0.2, math.sqrt(0.4)], [0.1, 0.3]],
        rtol=1e-14,
    )
    assert graph.pose_graph().num_poses == 6 and type(graph.pose_graph()) is PoseGraph


def test_landmark_file_matches_gtsam(tmp_path):
    gtsam = pytest.importorskip("gtsam")
    path = _write(tmp_path, LANDMARK_FILE)
    graph = read_toro(path)
    factors, values = gtsam.load2D(str(path))
    for k, vertex in enumerate(graph.vertex_ids.tolist()):
        pose = values.atPose2(vertex)
        np.testing.assert_allclose(
            _xytheta(graph.poses)[k], [pose.x(), pose.y(), pose.theta()], atol=1e-13
        )
    for k, landmark in enumerate(graph.landmark_ids.tolist()):
        np.testing.assert_allclose(
            graph.landmarks[k], values.atPoint2(gtsam.symbol("l", landmark)), atol=1e-13
        )
    assert values.size() == graph.num_poses + graph.num_landmarks
    sightings = [f for f in (factors.at(k) for k in range(factors.size())) if len(f.keys()) == 2]
    sightings = [f for f in sightings if type(f).__name__ == "BearingRangeFactor2D"]
    br = graph.bearing_range
    assert len(sightings) == len(br)
    for k, factor in enumerate(sightings):
        pose_key, landmark_key = factor.keys()
        assert pose_key == graph.vertex_ids[br.pose[k]]
        assert landmark_key == gtsam.symbol("l", int(graph.landmark_ids[br.landmark[k]]))
        measured = factor.measured()
        np.testing.assert_allclose(
            [measured.bearing().theta(), measured.range()], [br.bearing[k], br.range[k]], 1e-15
        )
        np.testing.assert_allclose(
            factor.noiseModel().sigmas(),
            1 / np.diagonal(np.asarray(br.sqrt_information[k])),
            rtol=1e-15,
        )
    # the costs at values that are not the initial ones (the dead reckoning fits the odometry)
    poses = graph.poses.rplus(np.linspace(-0.1, 0.2, graph.num_poses * 3).reshape(-1, 3))
    landmarks = np.asarray(graph.landmarks) + 0.3
    moved = gtsam.Values()
    for k, vertex in enumerate(graph.vertex_ids.tolist()):
        moved.insert(vertex, gtsam.Pose2(*_xytheta(poses)[k]))
    for k, landmark in enumerate(graph.landmark_ids.tolist()):
        moved.insert(gtsam.symbol("l", landmark), landmarks[k])
    moved_graph = graph.replace(poses=poses, landmarks=landmarks)
    total = float(cost(moved_graph.pose_graph())) + _sightings_cost(moved_graph)
    np.testing.assert_allclose(total, factors.error(moved), rtol=1e-12)


def _full_noise_file(order):
    """TORO_FILE's poses with one full symmetric noise matrix written in `order`."""
    m = {"11": 2.0, "12": 0.1, "13": 0.2, "22": 3.0, "23": 0.3, "33": 4.0}
    keys = (
        ("11", "12", "13", "22", "23", "33")
        if order == "g2o"
        else ("11", "12", "22", "33", "13", "23")
    )
    noise = " ".join(str(m[k]) for k in keys)
    lines = [line for line in TORO_FILE.splitlines() if line.startswith("VERTEX2")]
    lines += [" ".join(line.split()[:6]) + " " + noise for line in TORO_FILE.splitlines()
              if line.startswith("EDGE2")]  # fmt: skip
    return "\n".join(lines) + "\n", np.array([[2, 0.1, 0.2], [0.1, 3, 0.3], [0.2, 0.3, 4]])


def test_toro_noise_layouts(tmp_path):
    graph = read_toro(_write(tmp_path, TORO_FILE, "w.graph"))
    assert type(graph) is PoseGraph
    np.testing.assert_array_equal(graph.vertex_ids, [10, 12, 13, 17])
    np.testing.assert_array_equal(graph.edges, [[0, 1], [1, 2], [2, 3], [3, 0]])
    # `a 0 b c 0 0`: TORO order (m11 m12 m22 m33 m13 m23), a covariance (GTSAM's GRAPH)
    np.testing.assert_allclose(graph.information[0], np.diag([2, 4, 25.0]), rtol=1e-13)
    # `a 0 0 b 0 c`: g2o order, a covariance (GTSAM's COV)
    np.testing.assert_allclose(graph.information[2], np.diag([1, 0.25, 1 / 0.09]), rtol=1e-13)
    for order in ("toro", "g2o"):
        text, matrix = _full_noise_file(order)
        path = _write(tmp_path, text, f"{order}.graph")
        as_information = read_toro(path, noise_format=order).information
        np.testing.assert_allclose(as_information, np.broadcast_to(matrix, (4, 3, 3)), rtol=1e-13)
        covariance = {"toro": "graph", "g2o": "cov"}[order]
        as_covariance = read_toro(path, noise_format=covariance).information
        np.testing.assert_allclose(as_covariance @ matrix, np.broadcast_to(np.eye(3), (4, 3, 3)),
                                   atol=1e-13)  # fmt: skip
        with pytest.raises(ToroError, match=r"\.graph:5: noise .* fits neither"):
            read_toro(path)


@pytest.mark.parametrize("noise_format", ["auto", "graph", "cov", "toro", "g2o"])
def test_toro_noise_formats_match_gtsam(tmp_path, noise_format):
    gtsam = pytest.importorskip("gtsam")
    if noise_format == "auto":
        path = _write(tmp_path, TORO_FILE, "w.graph")
    else:
        text, _ = _full_noise_file("toro" if noise_format in ("graph", "toro") else "g2o")
        path = _write(tmp_path, text, "full.graph")
    name = "NoiseFormat" + noise_format.upper()
    factors, values = gtsam.load2D(str(path), noiseFormat=getattr(gtsam.NoiseFormat, name))
    graph = read_toro(path, noise_format=noise_format)
    for k, vertex in enumerate(graph.vertex_ids.tolist()):
        pose = values.atPose2(vertex)
        np.testing.assert_allclose(
            _xytheta(graph.poses)[k], [pose.x(), pose.y(), pose.theta()], atol=1e-15
        )
    assert factors.error(values) > 1e-2
    np.testing.assert_allclose(float(cost(graph)), factors.error(values), rtol=1e-12)


def _rpy_file(information_upper):
    """A 3D TORO file: four poses (ids 3, 4, 7, 9), a loop of four EDGE3 lines."""
    poses = {3: (0, 0, 0, 0, 0, 0), 4: (1, 0.1, -0.2, 0.1, -0.2, 0.3),
             7: (1.5, 1.2, 0.1, -0.3, 0.2, 1.7), 9: (0.2, 1.1, 0.3, 0.5, 0.1, 3.0)}  # fmt: skip
    edges = [(3, 4, (1.1, 0, -0.1, 0.05, -0.1, 0.2)), (4, 7, (0.4, 1.0, 0.2, -0.2, 0.3, 1.5)),
             (7, 9, (-1.2, 0.3, 0.1, 0.6, 0.0, 1.2)), (9, 3, (0.1, 0.2, -0.1, -0.4, 0.1, 3.1))]  # fmt: skip
    info = " ".join(str(v) for v in information_upper)
    lines = [f"VERTEX3 {v} " + " ".join(map(str, p)) for v, p in poses.items()]
    lines += [f"EDGE3 {i} {j} " + " ".join(map(str, z)) + " " + info for i, j, z in edges]
    return "\n".join(lines) + "\n"


def _information_upper():
    rng = np.random.default_rng(3)
    a = rng.normal(size=(6, 6))
    matrix = a @ a.T + 6 * np.eye(6)
    return matrix, matrix[np.triu_indices(6)]


def test_toro_3d_rotations_and_information(tmp_path):
    matrix, upper = _information_upper()
    graph = read_toro(_write(tmp_path, _rpy_file(upper), "g.graph"))
    assert graph.dim == 3
    np.testing.assert_array_equal(graph.vertex_ids, [3, 4, 7, 9])
    # R = Rz(yaw) Ry(pitch) Rx(roll)
    from scipy.spatial.transform import Rotation

    expected = Rotation.from_euler("ZYX", [0.3, -0.2, 0.1]).as_matrix()
    np.testing.assert_allclose(graph.poses[1].rotation().as_matrix(), expected, atol=1e-15)
    np.testing.assert_allclose(graph.poses[1].translation(), [1, 0.1, -0.2])
    # GTSAM's order (ω, v) swapped into lieax's (v, ω)
    swap = np.r_[3:6, 0:3]
    np.testing.assert_allclose(graph.information[2], matrix[swap][:, swap], rtol=1e-12)


def test_toro_3d_matches_gtsam(tmp_path):
    gtsam = pytest.importorskip("gtsam")
    _, upper = _information_upper()
    path = _write(tmp_path, _rpy_file(upper), "g.graph")
    graph = read_toro(path)
    factors, values = gtsam.load3D(str(path))
    for k, vertex in enumerate(graph.vertex_ids.tolist()):
        pose = values.atPose3(vertex)
        np.testing.assert_allclose(graph.poses[k].as_matrix(), pose.matrix(), atol=1e-14)
    assert factors.error(values) > 1e-2
    np.testing.assert_allclose(float(cost(graph)), factors.error(values), rtol=1e-12)


def test_round_trip_through_g2o(tmp_path):
    graph = read_toro(_write(tmp_path, TORO_FILE, "w.graph"))
    write_g2o(tmp_path / "w.g2o", graph)
    again = read_g2o(tmp_path / "w.g2o")
    np.testing.assert_array_equal(again.vertex_ids, graph.vertex_ids)
    np.testing.assert_array_equal(again.edges, graph.edges)
    np.testing.assert_allclose(again.poses.parameters(), graph.poses.parameters(), atol=1e-15)
    np.testing.assert_allclose(again.information, graph.information, rtol=1e-12)


def test_solvers_refuse_sightings(tmp_path):
    graph = read_toro(_write(tmp_path, LANDMARK_FILE))
    for solve in (optimize, to_factor_graph):
        with pytest.raises(ValueError, match="5 bearing-range sightings.*pose_graph"):
            solve(graph)


@pytest.mark.parametrize(
    "text, line, message",
    [
        ("VERTEX2 0 0 0 0\nEDGE2 0 1 1 0 0 1 0 1 1 0\n", 2, "EDGE2 needs 11 fields, got 10"),
        ("VERTEX2 0 0 0 0\nVERTEX2 1 0 x 0\n", 2, "expected a number, got 'x'"),
        ("VERTEX2 0 0 0 0\nVERTEX2 1.5 0 0 0\n", 2, "expected an integer id, got '1.5'"),
        ("VERTEX2 0 0 0 0\nVERTEX2 -1 0 0 0\n", 2, "negative"),
        ("VERTEX2 0 0 0 nan\n", 1, "non-finite"),
        ("VERTEX2 0 0 0 0\n\nVERTEX2 0 1 0 0\n", 3, "pose 0 already defined on line 1"),
        ("EDGE2 0 0 1 0 0 1 0 1 1 0 0\n", 1, "joins pose 0 to itself"),
        ("EDGE2 0 1 1 0 0 1 0.1 1 1 0 0\n", 1, "fits neither"),
        ("EDGE2 0 1 1 0 0 1 0 -1 1 0 0\n", 1, "covariance matrix is not positive definite"),
        ("BR 0 1 0.1 2.0 0 0.1\n", 1, "BR sigmas must be positive"),
        ("VERTEX2 0 0 0 0\nVERTEX3 1 0 0 0 0 0 0\n", 2, "2D and 3D lines mixed"),
        (
            "VERTEX3 1 0 0 0 0 0 0\nEDGE3 1 2 0 0 0 0 0 0" + " 1" * 21 + "\n",
            2,
            "refers to pose 2, which the file does not define",
        ),  # fmt: skip
        ("VERTEX3 1 0 0 0 0 0 0\nEDGE3 1 2 0 0 0 0 0 0\n", 2, "EDGE3 needs 29 fields, got 8"),
        ("VERTEX3 1 0 0 0 0 0 0\nEDGE3 1 1 0 0 0 0 0 0" + " 1" * 21 + "\n", 2, "to itself"),
    ],
)
def test_malformed_lines_name_file_and_line(tmp_path, text, line, message):
    path = _write(tmp_path, text, "bad.graph")
    with pytest.raises(ToroError, match=rf"bad\.graph:{line}: .*{message}"):
        read_toro(path)


def test_unknown_tags_warn_and_empty_files_are_refused(tmp_path):
    path = _write(tmp_path, "EQUIV 0 1\nVERTEX2 0 0 0 0 # a comment\n", "w.graph")
    with pytest.warns(ToroWarning, match="skipped 1 lines .*'EQUIV' ×1"):
        graph = read_toro(path)
    assert graph.num_poses == 1
    with pytest.raises(ToroError, match="no poses"):
        read_toro(_write(tmp_path, "# nothing\n", "empty.graph"))
    with pytest.raises(ValueError, match="noise_format must be one of"):
        read_toro(path, noise_format="information")


@pytest.mark.slow
def test_landmark_slam_reaches_gtsams_cost(tmp_path):
    """The LandmarkGraph docstring's problem, solved by lieax.factorgraph, ends at the cost of
    GTSAM's Levenberg-Marquardt on load2D's graph of the same file."""
    gtsam = pytest.importorskip("gtsam")
    import jax.numpy as jnp

    from lieax.factorgraph import Factor, FactorGraph, Var

    def bearing_range(pose, landmark, measured):
        local = pose.inverse() @ landmark
        error = jnp.arctan2(local[1], local[0]) - measured[0]
        wrapped = jnp.arctan2(jnp.sin(error), jnp.cos(error))
        return jnp.stack([wrapped, jnp.linalg.norm(local) - measured[1]])

    path = _write(tmp_path, LANDMARK_FILE)
    graph = read_toro(path)
    factor_graph, poses = to_factor_graph(graph.pose_graph())
    landmarks = Var(graph.landmarks, name="landmarks")
    br = graph.bearing_range
    sightings = Factor(
        bearing_range,
        (poses[br.pose], landmarks[br.landmark]),
        jnp.stack([br.bearing, br.range], -1),
        sqrt_information=br.sqrt_information,
        name="bearing-range",
    )
    result = FactorGraph([*factor_graph.factors, sightings]).solve()
    factors, values = gtsam.load2D(str(path))
    optimized = gtsam.LevenbergMarquardtOptimizer(factors, values).optimize()
    np.testing.assert_allclose(float(result.cost), factors.error(optimized), rtol=1e-6)
