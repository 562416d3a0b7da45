"""Tests of `lieax.graph.read_g2o` on a corpus of unusual and malformed g2o files written here from
tables: each file is either read as GTSAM's `readG2o` reads it (compared with GTSAM where it is
installed; the lieax-side assertions always run) or refused with a `G2oError` naming the file and
the line; then the information-matrix policies, quaternion normalisation and writing back what
was read.

GTSAM differs on purpose where it reads silently what is wrong (too few fields read as zeros,
extra fields ignored, self-loops, edges to undefined vertices, information matrices that are not
positive definite taken as they are) and where it has a quirk (a `#` comment line before the
edges ends its reading of edges): those cases are not compared.
"""

import re
import warnings

import numpy as np
import pytest

from lieax import graph as lg
from lieax.graph import G2oWarning

INFO2 = "4 0.5 0.1 3 0.2 10"
V2 = ["VERTEX_SE2 0 0 0 0", "VERTEX_SE2 1 1 0.5 0.3", "VERTEX_SE2 2 2 1 -0.2"]
E2 = [f"EDGE_SE2 0 1 1 0.5 0.3 {INFO2}", f"EDGE_SE2 1 2 1 0.5 -0.5 {INFO2}"]

_OMEGA3 = np.diag([1.0, 2.0, 3.0, 40.0, 50.0, 60.0])
_OMEGA3[0, 4] = _OMEGA3[4, 0] = 0.5
_OMEGA3[1, 3] = _OMEGA3[3, 1] = -0.3
INFO3 = " ".join(str(float(x)) for x in _OMEGA3[np.triu_indices(6)])
Q = "0.1 -0.2 0.3 0.9273618495495703"  # unit to 16 digits
V3 = ["VERTEX_SE3:QUAT 0 0 0 0 0 0 0 1", f"VERTEX_SE3:QUAT 1 1 0.5 -0.2 {Q}"]
E3 = [f"EDGE_SE3:QUAT 0 1 1 0.5 -0.2 {Q} {INFO3}"]


def lines(*rows, end="\n"):
    return end.join(rows) + end


# name: (file contents, regex the one G2oWarning must match or None for no warning, compare with
# GTSAM)
READ = {
    "plain 2D": (lines(*V2, *E2), None, True),
    "plain 3D": (lines(*V3, *E3), None, True),
    "negative ids": (
        lines(
            "VERTEX_SE2 -7 0 0 0",
            "VERTEX_SE2 -1 1 0.5 0.3",
            "VERTEX_SE2 4 2 1 -0.2",
            f"EDGE_SE2 -7 -1 1 0.5 0.3 {INFO2}",
            f"EDGE_SE2 -1 4 1 0.5 -0.5 {INFO2}",
            "FIX -7",
        ),
        None,
        True,
    ),
    "utf-8 byte-order mark": (("\ufeff" + lines(*V2, *E2)).encode("utf-8"), None, True),
    "windows line endings": (lines(*V2, *E2, end="\r\n"), None, True),
    "tabs": (lines(*V2, *E2).replace(" ", "\t"), None, True),
    "latin-1 comment": (lines(*V2, *E2).encode() + b"# caf\xe9 \xb0\xff\n", None, True),
    "utf-8 comment": (("# café — ü\n" + lines(*V2, *E2)).encode("utf-8"), None, False),
    "inline comment": (lines(V2[0] + " # origin", *V2[1:], *E2), None, True),
    "tutorial params and landmarks": (
        lines(
            "TUTORIAL_PARAMS_SE2 0 0 0 0 0",
            *V2,
            "VERTEX_XY 10 1 2",
            "VERTEX_XY 11 3 4",
            *E2,
            "EDGE_SE2_XY 0 10 1 2 1 0 1",
            "EDGE_SE2_XY 1 11 1 2 1 0 1",
        ),
        r"skipped 5 lines.*'TUTORIAL_PARAMS_SE2' ×1, 'VERTEX_XY' ×2, 'EDGE_SE2_XY' ×2",
        True,
    ),
    "other 3D tags": (
        lines("PARAMS_SE3OFFSET 0 0 0 0 0 0 0 1", *V3, "VERTEX_TRACKXYZ 9 1 2 3", *E3),
        r"'PARAMS_SE3OFFSET' ×1, 'VERTEX_TRACKXYZ' ×1",
        True,
    ),
    "many unknown tags": (
        lines(*V2, *E2, *(f"TAG{k} 1 2" for k in range(15))),
        r"skipped 15 lines .*'TAG0' ×1, .*'TAG9' ×1 and 5 other tags\)",
        True,
    ),
    "edges only": (lines(*E2), None, True),
    "vertices only": (lines(*V2), None, True),
    "FIX lines": (lines(*V2, *E2, "FIX 0", "FIX 2 0"), None, True),
    "quaternions with few digits": (
        lines(*V3, *E3).replace(Q, "0.1 -0.2 0.3 0.93"),
        r"\.g2o:2: normalised 2 quaternions .* more than 0\.001 \(at most 0\.00245",
        True,
    ),
    "quaternion inside the tolerance": (
        lines(*V3, *E3).replace(Q, "0.1 -0.2 0.3 0.9278"),
        None,
        True,
    ),
}

# name: (file contents, line named or None (the file as a whole), regex of the message, whether
# GTSAM refuses it too)
REFUSE = {
    "word for a number": (
        lines(V2[0], "VERTEX_SE2 1 1 zero 0.3"),
        2,
        "expected a number, got 'zero'",
        True,
    ),
    "word for an id": (
        lines(V2[0], "VERTEX_SE2 one 1 0.5 0.3"),
        2,
        "integer vertex id, got 'one'",
        False,
    ),
    "fractional id": (lines(*V2, "EDGE_SE2 0 1.5 1 0 0 1 0 0 1 0 1"), 4, "got '1.5'", False),
    "too few fields": (
        lines(*V2, E2[0].rsplit(" ", 1)[0]),
        4,
        "EDGE_SE2 needs 11 fields, got 10",
        False,
    ),
    "too many vertex fields": (lines(V2[0] + " 9", *V2[1:]), 1, "needs 4 fields, got 5", False),
    "too many edge fields": (lines(*V2, E2[0] + " 1 2"), 4, "needs 11 fields, got 13", False),
    "NaN": (lines(V2[0], "VERTEX_SE2 1 nan 0.5 0.3"), 2, "non-finite value nan", True),
    "infinite information": (lines(*V2, E2[0], E2[1].replace(" 10", " inf")), 5, "value inf", True),
    # GTSAM reads "-inf" (and "nan" not); lieax refuses every non-finite number
    "negative infinity": (lines(*V3, *E3).replace(" 0.5 -0.2", " -inf -0.2", 1), 2, "-inf", False),
    "duplicate vertex": (
        lines(*V2, "VERTEX_SE2 1 0 0 0"),
        4,
        "vertex 1 already defined on line 2",
        True,
    ),
    "edge to a missing vertex": (
        lines(*V2, "EDGE_SE2 1 7 1 0 0 1 0 0 1 0 1"),
        4,
        "vertex 7",
        False,
    ),
    "FIX of a missing vertex": (lines(*V2, *E2, "FIX 0 9"), 6, "FIX refers to vertex 9", False),
    "FIX of a word": (lines(*V2, "FIX zero"), 4, "got 'zero'", False),
    "FIX without ids": (lines(*V2, "FIX"), 4, "at least one vertex id", False),
    "mixed 2D and 3D": (lines(*V2, V3[1]), 4, "VERTEX_SE3:QUAT in a 2D file", False),
    "id beyond int64": (
        lines(V2[0], "VERTEX_SE2 9223372036854775808 0 0 0"),
        2,
        "int64 range",
        False,
    ),
    "negative id beyond int64": (
        lines(V2[0], "VERTEX_SE2 -9223372036854775809 0 0 0"),
        2,
        "outside the int64 range",
        False,
    ),
    "id beyond uint64": (
        lines(*V2, "VERTEX_SE2 99999999999999999999 0 0 0"),
        4,
        "int64 range",
        True,
    ),
    "self-loop": (
        lines(*V2, "EDGE_SE2 2 2 1 0 0 1 0 0 1 0 1"),
        4,
        "joins vertex 2 to itself",
        False,
    ),
    "zero quaternion": (lines(*V3, "VERTEX_SE3:QUAT 5 0 0 0 0 0 0 0"), 3, "no rotation", False),
    "no positive eigenvalue": (
        lines(*V2, "EDGE_SE2 0 1 1 0 0 -1 0 0 -2 0 0"),
        4,
        "no positive eigenvalue",
        False,
    ),
    "utf-16": (lines(*V2).encode("utf-16"), 1, "UTF-16", False),
    "empty file": ("", None, "no pose-graph vertices or edges", False),
    "only comments and blank lines": (
        lines("# nothing", "", "   ", "\t"),
        None,
        "no pose-graph",
        False,
    ),
    "only landmarks": (lines("VERTEX_XY 0 1 2"), None, "only skipped tags: VERTEX_XY", False),
}


def write(tmp_path, name, contents):
    path = tmp_path / (name.replace(" ", "_") + ".g2o")
    if isinstance(contents, str):
        path.write_bytes(contents.encode("latin-1"))
    else:
        path.write_bytes(contents)
    return path


def read_recording(path, **kwargs):
    """`read_g2o(path)` and the `G2oWarning`s it raised."""
    with warnings.catch_warnings(record=True) as caught:
        warnings.simplefilter("always")
        graph = lg.read_g2o(path, **kwargs)
    return graph, [w for w in caught if issubclass(w.category, G2oWarning)]


def test_corpus_file_names_are_distinct():
    assert not set(READ) & set(REFUSE)


@pytest.mark.parametrize("name", list(READ))
def test_read(tmp_path, name):
    contents, warning, _ = READ[name]
    path = write(tmp_path, name, contents)
    graph, caught = read_recording(path)
    if warning is None:
        assert not caught, [str(w.message) for w in caught]
    else:
        assert len(caught) == 1
        assert str(caught[0].message).startswith(str(path))
        assert re.search(warning, str(caught[0].message)), str(caught[0].message)
    reference = lg.read_g2o(write(tmp_path, "reference", lines(*V2, *E2)))
    if name in ("plain 2D", "utf-8 byte-order mark", "windows line endings", "tabs"):
        # the same graph as the plain file, whatever the bytes around it
        np.testing.assert_array_equal(graph.edges, reference.edges)
        np.testing.assert_array_equal(graph.poses.parameters(), reference.poses.parameters())
        np.testing.assert_array_equal(graph.information, reference.information)
    if graph.dim == 3:
        q = np.asarray(graph.poses.parameters())[:, :4]
        np.testing.assert_allclose(np.linalg.norm(q, axis=1), 1.0, atol=1e-15)


@pytest.mark.parametrize("name", [name for name, case in READ.items() if case[2]])
def test_read_agrees_with_gtsam(tmp_path, name):
    contents = READ[name][0]
    path = write(tmp_path, name, contents)
    graph, _ = read_recording(path)
    gtsam = pytest.importorskip("gtsam")
    factors, values = gtsam.readG2o(str(path), graph.dim == 3)
    at = values.atPose3 if graph.dim == 3 else values.atPose2
    keys = [int(v) % 2**64 for v in graph.vertex_ids]  # GTSAM keys are unsigned
    matrices = np.asarray(graph.poses.as_matrix())
    for key, matrix in zip(keys, matrices):
        np.testing.assert_allclose(at(key).matrix(), matrix, atol=1e-12)
    between = [
        factors.at(k)
        for k in range(factors.size())
        if factors.at(k) is not None and "Between" in type(factors.at(k)).__name__
    ]
    assert len(between) == len(graph.edges)
    measured = np.asarray(graph.measurements.as_matrix())
    # GTSAM orders the SE3 tangent rotation first; g2o and lieax translation first
    swap = [3, 4, 5, 0, 1, 2] if graph.dim == 3 else [0, 1, 2]
    for factor, (i, j), z, omega in zip(between, graph.edges, measured, graph.information):
        assert list(factor.keys()) == [keys[i], keys[j]]
        np.testing.assert_allclose(factor.measured().matrix(), z, atol=1e-12)
        root = factor.noiseModel().R()
        np.testing.assert_allclose((root.T @ root)[np.ix_(swap, swap)], omega, rtol=1e-12)


@pytest.mark.parametrize("name", list(REFUSE))
def test_refuse(tmp_path, name):
    contents, line, message, _ = REFUSE[name]
    path = write(tmp_path, name, contents)
    with warnings.catch_warnings():
        warnings.simplefilter("ignore", G2oWarning)
        with pytest.raises(lg.G2oError, match=message) as info:
            lg.read_g2o(path)
    assert str(info.value).startswith(f"{path}:" if line is None else f"{path}:{line}: ")


@pytest.mark.parametrize("name", [name for name, case in REFUSE.items() if case[3]])
def test_gtsam_refuses_too(tmp_path, name):
    path = write(tmp_path, name, REFUSE[name][0])
    gtsam = pytest.importorskip("gtsam")
    with pytest.raises(RuntimeError):
        gtsam.readG2o(str(path), "SE3" in REFUSE[name][0])


# ---- information matrices that are not positive definite ----------------------------------------

INDEFINITE = np.array(
    [[4.0, 3.0, 0.0], [3.0, 1.0, 0.0], [0.0, 0.0, 2.0]]
)  # eigenvalues -1.24, 2, 6.24
SINGULAR = np.diag([5.0, 0.0, 1.0])  # a zero row: GTSAM reads it, Cholesky fails


def _edge(i, j, omega):
    return f"EDGE_SE2 {i} {j} 1 0.5 0.3 " + " ".join(
        str(float(x)) for x in omega[np.triu_indices(3)]
    )


def _policy_file(tmp_path):
    good = np.array([[4.0, 0.5, 0.1], [0.5, 3.0, 0.2], [0.1, 0.2, 10.0]])
    text = lines(*V2, _edge(0, 1, good), _edge(1, 2, INDEFINITE), _edge(0, 2, SINGULAR))
    return write(tmp_path, "not_pd", text), good


def test_nearest_information_is_eigenvalue_clipping(tmp_path):
    path, good = _policy_file(tmp_path)
    graph, caught = read_recording(path)
    assert len(caught) == 1
    message = str(caught[0].message)
    assert message.startswith(f"{path}:5: 2 of 3 edges") and "information='nearest'" in message
    omega = np.asarray(graph.information)
    np.testing.assert_allclose(omega[0], good, rtol=1e-12)  # positive definite: untouched
    for repaired, original in zip(omega[1:], [INDEFINITE, SINGULAR]):
        eigenvalues = np.linalg.eigvalsh(original)
        floor = 1e-9 * eigenvalues[-1]
        np.testing.assert_allclose(repaired, repaired.T, rtol=0, atol=0)
        np.testing.assert_allclose(
            np.linalg.eigvalsh(repaired), np.maximum(eigenvalues, floor), rtol=1e-9, atol=1e-12
        )
        # Higham's optimum: the Frobenius distance is that of the clipped eigenvalues alone
        distance = np.linalg.norm(repaired - original)
        np.testing.assert_allclose(distance, np.linalg.norm(np.minimum(eigenvalues - floor, 0)))
        # and no further than dropping the off-diagonal entries
        diagonal = np.diag(np.maximum(np.diag(original), 1e-9 * np.diag(original).max()))
        assert distance <= np.linalg.norm(diagonal - original) + 1e-12
    # the graph is usable: the cost is finite and the square roots factor the repaired matrices
    root = np.asarray(graph.between.sqrt_information)
    np.testing.assert_allclose(np.swapaxes(root, 1, 2) @ root, omega, rtol=1e-9, atol=1e-12)
    assert np.isfinite(float(lg.cost(graph)))


def test_diagonal_and_raise_policies(tmp_path):
    path, good = _policy_file(tmp_path)
    graph, caught = read_recording(path, information="diagonal")
    assert len(caught) == 1 and "information='diagonal'" in str(caught[0].message)
    omega = np.asarray(graph.information)
    np.testing.assert_allclose(omega[0], good, rtol=1e-12)
    np.testing.assert_allclose(omega[1], np.diag([4.0, 1.0, 2.0]), rtol=1e-12, atol=0)
    np.testing.assert_allclose(omega[2], np.diag([5.0, 5e-9, 1.0]), rtol=1e-12, atol=0)
    with pytest.raises(lg.G2oError, match="not positive definite") as info:
        lg.read_g2o(path, information="raise")
    assert str(info.value).startswith(f"{path}:5: ")
    with pytest.raises(lg.G2oError, match="no positive diagonal entry") as info:
        lg.read_g2o(
            write(tmp_path, "neg", lines(*V2, _edge(0, 1, -np.eye(3)))), information="diagonal"
        )
    assert str(info.value).startswith(f"{tmp_path / 'neg.g2o'}:4: ")
    with pytest.raises(ValueError, match="information must be one of"):
        lg.read_g2o(path, information="clip")


def test_one_warning_for_many_repairs(tmp_path):
    edges = [_edge(k % 3, (k + 1) % 3, INDEFINITE * (1 + k)) for k in range(40)]
    _, caught = read_recording(write(tmp_path, "many", lines(*V2, *edges)))
    assert len(caught) == 1 and ":4: 40 of 40 edges" in str(caught[0].message)


def test_write_what_was_read(tmp_path):
    """A graph read with repairs and normalisations, written back, reads without warnings and
    equal values; negative ids survive."""
    path, _ = _policy_file(tmp_path)
    text = path.read_text().replace("VERTEX_SE2 0 ", "VERTEX_SE2 -3 ").replace(" 0 1 1", " -3 1 1")
    text = text.replace("EDGE_SE2 0 2", "EDGE_SE2 -3 2") + "FIX -3\n"
    path.write_text(text)
    graph, caught = read_recording(path)
    assert len(caught) == 1
    np.testing.assert_array_equal(graph.vertex_ids, [-3, 1, 2])
    out = tmp_path / "out.g2o"
    lg.write_g2o(out, graph)
    back, caught = read_recording(out)
    assert not caught
    np.testing.assert_array_equal(back.vertex_ids, graph.vertex_ids)
    np.testing.assert_array_equal(back.fixed, [0])
    np.testing.assert_allclose(back.information, graph.information, rtol=1e-12, atol=1e-15)

    three = write(tmp_path, "q", lines(*V3, *E3).replace(Q, "0.1 -0.2 0.3 0.93"))
    graph, caught = read_recording(three)
    assert len(caught) == 1
    lg.write_g2o(out, graph)
    back, caught = read_recording(out)
    assert not caught
    np.testing.assert_allclose(back.poses.parameters(), graph.poses.parameters(), atol=1e-15)
