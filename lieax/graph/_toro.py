r"""Reading TORO and GTSAM text datasets (the files GTSAM's `load2D` and `load3D` read): pose
graphs as `w10000.graph` (2D) and 3D TORO files, and 2D landmark SLAM as
`victoria_park.txt`.

Lines, as GTSAM 4.3's `gtsam/slam/dataset.cpp` parses them (`parseVertexPose`,
`parseVertexLandmark`, `parseEdge`, the bearing-range parser, `load2D`; `parseVertexPose3`, the
`Pose3` measurement parser, `load3D`):

| line | fields |
|---|---|
| `VERTEX2 id x y θ` (also `VERTEX`, `VERTEX_SE2`) | pose |
| `EDGE2 i j x y θ n1 … n6` (also `EDGE`, `EDGE_SE2`, `ODOMETRY`) | $X_i^{-1}X_j$, six noise numbers |
| `VERTEX_XY id x y` | landmark |
| `BR i l b r σ_b σ_r` | bearing $b$ (radians) and range $r$ of landmark `l` from pose `i` |
| `LANDMARK i l x y v1 v2 v3` | landmark `l` at $(x, y)$ in pose `i`'s frame |
| `VERTEX3 id x y z roll pitch yaw` | pose, $R = R_z(\text{yaw})R_y(\text{pitch})R_x(\text{roll})$ |
| `EDGE3 i j x y z roll pitch yaw I11 … I16 I22 … I66` | $X_i^{-1}X_j$, 21 upper-triangle entries |

Noise, as GTSAM derives it:
- 2D edges (`noise_format`, GTSAM's `NoiseFormat`): the six numbers are a symmetric matrix $M$ in
  g2o's upper-triangle order $(m_{11}, m_{12}, m_{13}, m_{22}, m_{23}, m_{33})$ or TORO's
  $(m_{11}, m_{12}, m_{22}, m_{33}, m_{13}, m_{23})$, and $M$ is a covariance or an information.
  `"auto"` (GTSAM's default) decides per line from where the zeros are:
  $(a, 0, b, c, 0, 0)$ is TORO order, $(a, 0, 0, b, 0, c)$ g2o order, both read as
  **covariances** (GTSAM's `NoiseFormatGRAPH` and `NoiseFormatCOV`), anything else is refused;
  `"graph"`, `"cov"`, `"toro"` (TORO order, information) and `"g2o"` (g2o order, information)
  fix the reading. The tangent order $(x, y, \theta)$ is lieax's. (`VERTEX_SE2`/`EDGE_SE2` lines
  are read as `load2D` reads them, so under `"auto"` a g2o edge's information entries become a
  covariance; read g2o files with `read_g2o`, as GTSAM's `readG2o` does, or pass
  `noise_format="g2o"`.)
- `BR`: $\mathrm{diag}(\sigma_b, \sigma_r)$ as given. `LANDMARK`: the bearing and range of
  $(x, y)$, $b = \mathrm{atan2}(y, x)$, $r = \sqrt{x^2 + y^2}$, with
  $\sigma_b = \sqrt{v_1 / 10}$, $\sigma_r = \sqrt{v_1}$ when $|v_1 - v_3| < 10^{-4}$ (GTSAM takes
  the $x$-$y$ covariance as the uncertainty at 10 m), else $\sigma_b = \sigma_r = 1$.
- `EDGE3`: the 21 numbers are an information matrix that GTSAM reads in its own tangent order,
  rotation first ($\omega$, $v$), with no reordering (unlike g2o's `EDGE_SE3:QUAT`); lieax swaps
  the blocks into its translation-first order, so the costs are GTSAM's. (TORO's own order is
  translation first; for block-diagonal matrices with equal blocks, as in the public sets, the two
  readings agree.)

Ids and initial values, as `load2D` makes them: poses and landmarks are two id spaces (GTSAM keys
a landmark `l` as `Symbol('l', l)`), each ordered by id as GTSAM's `Values` iterates its keys, so
ids need not be contiguous (in `victoria_park.txt` poses and landmarks share one counter). Vertex
lines give initial values; then, in file order, an edge whose first pose has none starts it at
the identity, and an edge's second pose without one gets $X_i Z$; a bearing-range line's pose
without one starts at the identity and its landmark gets $t_i + R_i\,r\,(\cos b, \sin b)$.
`load3D` makes no values, so a 3D edge to a pose the file does not define is refused. (GTSAM's
own `sphere_smallnoise.graph` has `EDGE3` lines without the 21 information entries: `load3D`
reads on into the next line and stops after one factor; `read_toro` refuses the line.)

Differences from GTSAM, each refused with `ToroError` naming the file and line where GTSAM reads
on silently: a line with too few or too many fields, a word or a non-finite number where a number
belongs, a negative id (GTSAM wraps it to a large unsigned key), a duplicate vertex, a 2D edge
joining a pose to itself, a noise matrix that is not positive definite, 2D and 3D lines mixed.
`#` starts a comment; tags the reader does not know are skipped with one `ToroWarning` counting
them (GTSAM skips them silently).
"""

import collections
import dataclasses
import math
import os
import warnings

import jax.numpy as jnp
import numpy as np

from ..factorgraph import square_root_information
from ..groups import SE2, SE3, kernels
from ._graph import BetweenFactors, PoseGraph

_POSE2 = ("VERTEX2", "VERTEX", "VERTEX_SE2")
_EDGE2 = ("EDGE2", "EDGE", "EDGE_SE2", "ODOMETRY")
_LANDMARK2 = ("VERTEX_XY",)
_BEARING_RANGE = ("BR", "LANDMARK")
_POSE3 = ("VERTEX3",)
_EDGE3 = ("EDGE3",)
# tag -> (dimension, number of fields after the tag)
_TAGS = {
    **{tag: (2, 4) for tag in _POSE2},
    **{tag: (2, 11) for tag in _EDGE2},
    "VERTEX_XY": (2, 3),
    "BR": (2, 6),
    "LANDMARK": (2, 7),
    "VERTEX3": (3, 7),
    "EDGE3": (3, 29),
}
_NOISE_FORMATS = ("auto", "graph", "cov", "toro", "g2o")
# (order, is a covariance): the order maps the six numbers to M's upper triangle m11 m12 m13 m22
# m23 m33 (g2o's order is that triangle; TORO's is m11 m12 m22 m33 m13 m23).
_G2O_ORDER = (0, 1, 2, 3, 4, 5)
_TORO_ORDER = (0, 1, 4, 2, 5, 3)
_NOISE = {
    "graph": (_TORO_ORDER, True),
    "cov": (_G2O_ORDER, True),
    "toro": (_TORO_ORDER, False),
    "g2o": (_G2O_ORDER, False),
}
_LANDMARK_RANGE = 10.0  # GTSAM reads a LANDMARK line's x-y covariance as the one at 10 m
_LANDMARK_ISOTROPIC = 1e-4
_LISTED_TAGS = 10


class ToroError(ValueError):
    """A TORO or GTSAM text dataset that cannot be read; the message names the file and line."""


class ToroWarning(UserWarning):
    """A TORO or GTSAM text dataset read with lines skipped; the message says which."""


@dataclasses.dataclass(frozen=True)
class BearingRangeFactors:
    r"""Bearing-range sightings of 2D landmarks, one per `BR` or `LANDMARK` line: GTSAM's
    `BearingRangeFactor<Pose2, Point2>`, whose residual is
    $r = (\mathrm{wrap}(\mathrm{bearing}(X_i, l_k) - b),\ \lVert l_k - t_i\rVert - \rho)$ with
    $\mathrm{bearing}(X, l) = \mathrm{atan2}$ of $l$ in $X$'s frame, weighed by
    $\tfrac12\lVert R\,r\rVert^2$.

    **Fields:**

    - `pose`, `landmark`: numpy int64 `(m,)`: indices into the graph's poses and landmarks.
    - `bearing`: `(m,)` measured bearings $b$ (radians, in the pose's frame).
    - `range`: `(m,)` measured ranges $\rho$.
    - `sqrt_information`: `(m, 2, 2)` $R = \mathrm{diag}(1/\sigma_b, 1/\sigma_r)$.
    """

    pose: np.ndarray
    landmark: np.ndarray
    bearing: jnp.ndarray
    range: jnp.ndarray
    sqrt_information: jnp.ndarray

    def __len__(self):
        return int(self.pose.shape[0])


@dataclasses.dataclass(frozen=True, repr=False)
class LandmarkGraph(PoseGraph):
    """A 2D pose graph with landmarks: a `PoseGraph` (poses, ids, between factors) plus
    `landmarks` `(L, 2)` (initial positions, ordered by id), their file ids `landmark_ids` and
    the `bearing_range` sightings (`BearingRangeFactors`).

    `lieax.graph.optimize` and `to_factor_graph` model poses only and refuse a graph with
    sightings; `pose_graph()` is the pose part, to build the whole problem with
    `lieax.factorgraph`:

    ```python
    def bearing_range(pose, landmark, measured):  # GTSAM's BearingRangeFactor<Pose2, Point2>
        local = pose.inverse() @ landmark
        error = jnp.arctan2(local[1], local[0]) - measured[0]
        wrapped = jnp.arctan2(jnp.sin(error), jnp.cos(error))
        return jnp.stack([wrapped, jnp.linalg.norm(local) - measured[1]])

    graph = lieax.graph.read_toro("victoria_park.txt")
    factor_graph, poses = lieax.graph.to_factor_graph(graph.pose_graph())  # pose 0 fixed
    landmarks = Var(graph.landmarks, name="landmarks")
    br = graph.bearing_range
    sightings = Factor(bearing_range, (poses[br.pose], landmarks[br.landmark]),
                       jnp.stack([br.bearing, br.range], -1),
                       sqrt_information=br.sqrt_information, name="bearing-range")
    result = FactorGraph([*factor_graph.factors, sightings]).solve()
    ```
    """

    landmarks: jnp.ndarray = None
    landmark_ids: np.ndarray = None
    bearing_range: BearingRangeFactors = None

    @property
    def num_landmarks(self) -> int:
        return int(self.landmarks.shape[0])

    def pose_graph(self) -> PoseGraph:
        """The poses and between factors, without the landmarks and sightings."""
        return PoseGraph(self.poses, self.vertex_ids, self.between, self.priors, self.fixed)

    def __repr__(self):
        return (
            f"LandmarkGraph(SE2, {self.num_poses} poses, {self.num_edges} edges, "
            f"{self.num_landmarks} landmarks, {len(self.bearing_range)} bearing-range)"
        )


def read_toro(path, *, noise_format="auto", dtype=None) -> PoseGraph:
    r"""Read a TORO or GTSAM text dataset (what GTSAM's `load2D` / `load3D` read; the layouts,
    noise models and initial values are in the module docstring).

    **Arguments:**

    - `path`: the file.
    - `noise_format`: how the six noise numbers of a 2D edge read: `"auto"` (GTSAM's default),
      `"graph"`, `"cov"`, `"toro"` or `"g2o"` (GTSAM's `NoiseFormat`s; see the module docstring).
    - `dtype`: float dtype of the poses (default: JAX's default float).

    **Returns:** a `PoseGraph` (poses and vertex ids ordered by id) for a pose graph, as
    `read_g2o` returns; a `LandmarkGraph` (a `PoseGraph` with landmarks and bearing-range
    sightings) when a 2D file has `VERTEX_XY`, `BR` or `LANDMARK` lines.

    **Warns:** `ToroWarning` once, counting the lines of tags it does not read.

    **Raises:** `ToroError` (a `ValueError`) naming the file and line for a malformed line (field
    count, a word or non-finite number for a number, an id that is not an integer $\ge 0$), 2D
    and 3D lines mixed, a duplicate vertex, a self-loop, a 2D noise matrix whose zeros fit
    neither layout (`"auto"`) or that is not positive definite, a 3D edge naming a pose the file
    does not define; also for a file with no poses.
    """
    if noise_format not in _NOISE_FORMATS:
        raise ValueError(f"noise_format must be one of {_NOISE_FORMATS}, got {noise_format!r}.")
    path = os.fspath(path)
    lines, skipped = _read_lines(path)
    dims = {_TAGS[tag][0] for tag in lines}
    if len(dims) > 1:
        first = {
            d: min(numbers[0] for tag, (numbers, _) in lines.items() if _TAGS[tag][0] == d)
            for d in (2, 3)
        }
        raise ToroError(
            f"{path}:{max(first.values())}: 2D and 3D lines mixed (the first 2D line is "
            f"{first[2]}, the first 3D line {first[3]})."
        )
    if skipped:
        counts = list(skipped.items())
        listed = ", ".join(f"{tag!r} ×{n}" for tag, n in counts[:_LISTED_TAGS])
        warnings.warn(
            f"{path}: skipped {sum(skipped.values())} lines with tags lieax does not read "
            f"({listed}); read_toro reads {', '.join(_TAGS)}.",
            ToroWarning,
            stacklevel=2,
        )
    if not dims:
        raise ToroError(f"{path}: no poses (no {', '.join(_TAGS)} lines).")
    to_dtype = (lambda x: jnp.asarray(x)) if dtype is None else (lambda x: jnp.asarray(x, dtype))
    if dims == {3}:
        return _read_3d(lines, path, to_dtype)
    return _read_2d(lines, path, noise_format, to_dtype)


def _read_lines(path):
    """`({tag: ([line numbers], [the line's text after the tag])}, skipped tag counts)` for the
    known tags, each line's field count checked. (Lines are kept as text and split again per tag
    in one go: millions of small lists would keep Python's cyclic collector busy.)"""
    lines, skipped = collections.defaultdict(lambda: ([], [])), collections.Counter()
    with open(path, encoding="latin-1", newline="\n") as handle:
        for number, line in enumerate(handle, start=1):
            if "#" in line:
                line = line[: line.index("#")]
            fields = line.split(None, 1)
            if not fields:
                continue
            tag = fields[0]
            if tag not in _TAGS:
                skipped[tag] += 1
                continue
            rest = fields[1] if len(fields) > 1 else ""
            count = _TAGS[tag][1]
            found = len(rest.split())
            if found != count:
                raise ToroError(f"{path}:{number}: {tag} needs {count} fields, got {found}.")
            numbers, texts = lines[tag]
            numbers.append(number)
            texts.append(rest)
    return dict(lines), skipped


def _table(lines, tags, id_count, path):
    """`(line numbers (k,), ids (k, id_count) int64, numbers (k, n) float64)` of the lines of
    `tags` in file order, refusing the first bad field with its line."""
    numbers = np.asarray([n for tag in tags for n in lines.get(tag, ([], []))[0]], np.int64)
    texts = [t for tag in tags for t in lines.get(tag, ([], []))[1]]
    order = np.argsort(numbers, kind="stable")
    numbers = numbers[order]
    texts = [texts[k] for k in order.tolist()]
    count = _TAGS[tags[0]][1]
    tokens = " ".join(texts).split()
    try:  # Python's int and float parse ~10x faster than NumPy's string conversion
        ids = [list(map(int, tokens[c::count])) for c in range(id_count)]
        ids = np.asarray(ids, np.int64).T.reshape(len(texts), id_count)
        values = np.asarray(list(map(float, tokens)), np.float64).reshape(len(texts), count)
        values = values[:, id_count:]
    except (ValueError, OverflowError):
        for number, text in zip(numbers.tolist(), texts):
            fields = text.split()
            _ids(fields[:id_count], f"{path}:{number}")
            _numbers(fields[id_count:], f"{path}:{number}")
        raise
    for bad, message in (
        (np.any(ids < 0, axis=1), "an id is negative (ids are integers >= 0)"),
        (~np.all(np.isfinite(values), axis=1), "a non-finite value where a number belongs"),
    ):
        if np.any(bad):
            raise ToroError(f"{path}:{numbers[np.argmax(bad)]}: {message}.")
    return numbers, ids, values


def _ids(fields, where):
    for field in fields:
        try:
            value = int(field)
        except ValueError:
            raise ToroError(f"{where}: expected an integer id, got {field!r}.") from None
        if not 0 <= value < 2**63:
            raise ToroError(f"{where}: id {value} is not an integer in [0, 2^63).")


def _numbers(fields, where):
    for field in fields:
        try:
            float(field)
        except ValueError:
            raise ToroError(f"{where}: expected a number, got {field!r}.") from None


def _first_duplicate(ids, numbers, what, path):
    """Refuse the second definition of an id, naming both lines."""
    order = np.argsort(ids, kind="stable")
    same = ids[order][1:] == ids[order][:-1]
    if np.any(same):
        k = int(np.argmax(same))
        first, second = numbers[order[k]], numbers[order[k + 1]]
        raise ToroError(f"{path}:{second}: {what} {ids[order[k]]} already defined on line {first}.")


def _noise_matrices(values, noise_format, numbers, path):
    """`(M (m, 3, 3), is_covariance (m,))` from 2D edges' six noise numbers (see the module
    docstring)."""
    nonzero = values != 0
    if noise_format == "auto":
        graph = np.all(nonzero == [True, False, True, True, False, False], axis=1)
        cov = np.all(nonzero == [True, False, False, True, False, True], axis=1)
        bad = ~(graph | cov)
        if np.any(bad):
            k = int(np.argmax(bad))
            raise ToroError(
                f"{path}:{numbers[k]}: noise {values[k].tolist()} fits neither TORO's layout "
                "(a 0 b c 0 0) nor g2o's (a 0 0 b 0 c), which noise_format='auto' tells apart "
                "as GTSAM's load2D does; pass noise_format= ('graph', 'cov', 'toro' or 'g2o')."
            )
        toro, covariance = graph, np.ones(len(values), dtype=bool)
    else:
        order, is_covariance = _NOISE[noise_format]
        toro = np.full(len(values), order == _TORO_ORDER)
        covariance = np.full(len(values), is_covariance)
    upper = np.where(toro[:, None], values[:, list(_TORO_ORDER)], values[:, list(_G2O_ORDER)])
    rows, cols = np.triu_indices(3)
    matrices = np.zeros((len(values), 3, 3))
    matrices[:, rows, cols] = upper
    matrices[:, cols, rows] = upper
    return matrices, covariance


def _sqrt_information(matrices, covariance, numbers, path):
    """$R$ `(m, d, d)` of information (or covariance) matrices, refusing with the line of the
    first one that is not positive definite."""
    if not len(matrices):
        return matrices
    smallest = np.linalg.eigvalsh(matrices)[:, 0]
    bad = smallest <= 0
    if np.any(bad):
        k = int(np.argmax(bad))
        raise ToroError(
            f"{path}:{numbers[k]}: the noise {'covariance' if covariance[k] else 'information'} "
            f"matrix is not positive definite (smallest eigenvalue {smallest[k]:.3g})."
        )
    roots = np.zeros_like(matrices)
    for flag in (False, True):
        pick = covariance == flag
        if np.any(pick):
            roots[pick] = square_root_information(matrices[pick], "noise", covariance=flag)
    return roots


def _compose(pose, z):
    """GTSAM's `Pose2` product $X Z$ of `(cos, sin, x, y)` tuples."""
    c1, s1, x1, y1 = pose
    c2, s2, x2, y2 = z
    return (c1 * c2 - s1 * s2, s1 * c2 + c1 * s2, x1 + c1 * x2 - s1 * y2, y1 + s1 * x2 + c1 * y2)


def _bearing_range(lines, path):
    """`(line numbers, (k, 2) pose and landmark ids, bearings, ranges, (k, 2) sigmas)` of the
    `BR` and `LANDMARK` lines, in file order."""
    parts = []
    for tag in _BEARING_RANGE:
        if tag not in lines:
            continue
        numbers, ids, values = _table(lines, (tag,), 2, path)
        if tag == "BR":
            bearing, distance, sigmas = values[:, 0], values[:, 1], values[:, 2:4]
            bad = np.any(sigmas <= 0, axis=1)
            what = "BR sigmas must be positive"
        else:
            x, y, v1, v3 = values[:, 0], values[:, 1], values[:, 2], values[:, 4]
            bearing, distance = np.arctan2(y, x), np.hypot(x, y)
            isotropic = np.abs(v1 - v3) < _LANDMARK_ISOTROPIC
            bad = isotropic & (v1 <= 0)
            v1 = np.where(bad, 1.0, v1)
            sigmas = np.where(
                isotropic[:, None],
                np.stack([np.sqrt(v1 / _LANDMARK_RANGE), np.sqrt(v1)], axis=1),
                1.0,
            )
            what = "the LANDMARK variance must be positive"
        if np.any(bad):
            raise ToroError(f"{path}:{numbers[np.argmax(bad)]}: {what}.")
        parts.append((numbers, ids, bearing, distance, sigmas))
    if not parts:
        return np.zeros(0, np.int64), np.zeros((0, 2), np.int64), *np.zeros((2, 0)), np.ones((0, 2))
    order = np.argsort(np.concatenate([p[0] for p in parts]))
    return tuple(np.concatenate([p[k] for p in parts])[order] for k in range(5))


def _index(ids, known):
    """Positions of `ids` in the sorted array `known`."""
    return np.searchsorted(known, ids).astype(np.int64)


def _read_2d(lines, path, noise_format, to_dtype):
    pose_lines, pose_ids, pose_values = _table(lines, _POSE2, 1, path)
    _first_duplicate(pose_ids[:, 0], pose_lines, "pose", path)
    mark_lines, mark_ids, mark_values = _table(lines, _LANDMARK2, 1, path)
    _first_duplicate(mark_ids[:, 0], mark_lines, "landmark", path)
    edge_lines, edges, edge_values = _table(lines, _EDGE2, 2, path)
    loops = edges[:, 0] == edges[:, 1]
    if np.any(loops):
        k = int(np.argmax(loops))
        raise ToroError(f"{path}:{edge_lines[k]}: edge joins pose {edges[k, 0]} to itself.")
    matrices, covariance = _noise_matrices(edge_values[:, 3:], noise_format, edge_lines, path)
    root = _sqrt_information(matrices, covariance, edge_lines, path)
    theta = edge_values[:, 2]
    measured = np.stack([np.cos(theta), np.sin(theta), edge_values[:, 0], edge_values[:, 1]], 1)
    sight_lines, sightings, bearing, distance, sigmas = _bearing_range(lines, path)

    # initial values as load2D makes them: vertex lines, then edges and sightings in file order
    # (flat lists and tuples: a list per row would keep Python's cyclic collector busy)
    theta = pose_values[:, 2]
    columns = (np.cos(theta), np.sin(theta), pose_values[:, 0], pose_values[:, 1])
    poses = dict(zip(pose_ids[:, 0].tolist(), zip(*(c.tolist() for c in columns))))
    landmarks = dict(zip(mark_ids[:, 0].tolist(), zip(*mark_values.T.tolist())))
    events = np.argsort(np.concatenate([edge_lines, sight_lines]), kind="stable").tolist()
    first, second = np.concatenate([edges, sightings]).T.tolist()
    measured_rows = list(zip(*measured.T.tolist()))
    sighted_rows = list(zip(bearing.tolist(), distance.tolist()))
    edge_count = len(edges)
    for event in events:
        i, j = first[event], second[event]
        if i not in poses:
            poses[i] = (1.0, 0.0, 0.0, 0.0)
        if event < edge_count:
            if j not in poses:
                poses[j] = _compose(poses[i], measured_rows[event])
        elif j not in landmarks:
            b, r = sighted_rows[event - edge_count]
            c, s, x, y = poses[i]
            u, v = r * math.cos(b), r * math.sin(b)
            landmarks[j] = (x + c * u - s * v, y + s * u + c * v)
    if not poses:
        raise ToroError(f"{path}: no poses (no {', '.join(_POSE2 + _EDGE2)} lines).")

    ids = np.asarray(sorted(poses), dtype=np.int64)
    between = BetweenFactors(
        _index(edges[:, 0], ids),
        _index(edges[:, 1], ids),
        kernels.element(SE2, to_dtype(measured)),
        to_dtype(root),
    )
    pose_params = kernels.element(
        SE2, to_dtype(np.asarray([poses[v] for v in ids.tolist()], np.float64))
    )
    if not landmarks:
        return PoseGraph(pose_params, ids, between)
    landmark_ids = np.asarray(sorted(landmarks), dtype=np.int64)
    positions = np.asarray([landmarks[v] for v in landmark_ids.tolist()], np.float64)
    sighted = BearingRangeFactors(
        _index(sightings[:, 0], ids),
        _index(sightings[:, 1], landmark_ids),
        to_dtype(bearing),
        to_dtype(distance),
        to_dtype(np.eye(2) / sigmas[:, :, None]),
    )
    return LandmarkGraph(
        pose_params,
        ids,
        between,
        landmarks=to_dtype(positions.reshape(-1, 2)),
        landmark_ids=landmark_ids,
        bearing_range=sighted,
    )


def _se3_rows(values):
    r"""SE3 parameters `(k, 7)` (wxyz, t) from rows `x y z roll pitch yaw`: the quaternion of
    $R_z(\text{yaw}) R_y(\text{pitch}) R_x(\text{roll})$ (GTSAM's `Rot3::Ypr`), the product
    $q_z q_y q_x$ of the half-angle quaternions."""
    values = np.asarray(values, np.float64).reshape(-1, 6)
    half = values[:, 3:] / 2
    cr, cp, cy = np.cos(half).T
    sr, sp, sy = np.sin(half).T
    wxyz = np.stack(
        [
            cy * cp * cr + sy * sp * sr,
            cy * cp * sr - sy * sp * cr,
            cy * sp * cr + sy * cp * sr,
            sy * cp * cr - cy * sp * sr,
        ],
        axis=1,
    )
    return np.concatenate([wxyz, values[:, :3]], axis=1)


def _read_3d(lines, path, to_dtype):
    pose_lines, pose_ids, pose_values = _table(lines, _POSE3, 1, path)
    _first_duplicate(pose_ids[:, 0], pose_lines, "pose", path)
    edge_lines, edges, edge_values = _table(lines, _EDGE3, 2, path)
    if not len(pose_lines):
        raise ToroError(f"{path}: no VERTEX3 lines.")
    ids = np.unique(pose_ids[:, 0])
    index = _index(edges, ids).clip(max=len(ids) - 1)
    missing = ids[index] != edges
    if np.any(missing):
        k = int(np.argmax(np.any(missing, axis=1)))
        raise ToroError(
            f"{path}:{edge_lines[k]}: edge refers to pose {edges[k][np.argmax(missing[k])]}, "
            "which the file does not define (GTSAM's load3D makes no initial values)."
        )
    loops = edges[:, 0] == edges[:, 1]
    if np.any(loops):
        k = int(np.argmax(loops))
        raise ToroError(f"{path}:{edge_lines[k]}: edge joins pose {edges[k, 0]} to itself.")
    rows, cols = np.triu_indices(6)
    gtsam_order = np.zeros((len(edges), 6, 6))
    gtsam_order[:, rows, cols] = edge_values[:, 6:]
    gtsam_order[:, cols, rows] = edge_values[:, 6:]
    swap = np.r_[3:6, 0:3]  # GTSAM's (ω, v) to lieax's (v, ω)
    information = gtsam_order[:, swap][:, :, swap]
    root = _sqrt_information(information, np.zeros(len(edges), bool), edge_lines, path)
    poses = _se3_rows(pose_values[np.argsort(pose_ids[:, 0])])
    between = BetweenFactors(
        index[:, 0].copy(),
        index[:, 1].copy(),
        kernels.element(SE3, to_dtype(_se3_rows(edge_values[:, :6]))),
        to_dtype(root),
    )
    return PoseGraph(kernels.element(SE3, to_dtype(poses)), ids, between)
