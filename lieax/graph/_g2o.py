"""Reading and writing g2o pose-graph files (2D `VERTEX_SE2`/`EDGE_SE2`, 3D
`VERTEX_SE3:QUAT`/`EDGE_SE3:QUAT`, and `FIX`).

Layouts (g2o's, as GTSAM's `readG2o`/`writeG2o` read and write them):

| line | fields |
|---|---|
| `VERTEX_SE2 id x y θ` | pose |
| `EDGE_SE2 i j x y θ I11 I12 I13 I22 I23 I33` | measurement $X_i^{-1}X_j$, upper triangle of $\\Omega$ |
| `VERTEX_SE3:QUAT id x y z qx qy qz qw` | pose (quaternion scalar last) |
| `EDGE_SE3:QUAT i j x y z qx qy qz qw I11 … I16 I22 … I66` | 21 upper-triangle entries |
| `FIX id` | the vertex is held constant |

g2o orders the information of an SE3 edge as translation then rotation, like lieax's tangent
`(vx, vy, vz, ωx, ωy, ωz)` (GTSAM, whose tangent is rotation first, swaps the blocks on reading):
the matrix is used as read. The residual it weighs is lieax's $\\mathrm{Log}(Z^{-1}X_i^{-1}X_j)$,
GTSAM's `BetweenFactor` error, so costs agree with GTSAM's.

Files that have edges but no vertices get initial poses by composing the measurements along a
breadth-first spanning tree from the smallest id (`lieax.graph.spanning_tree_poses`).
"""

import os

import jax.numpy as jnp
import numpy as np

from ..groups._se2 import SE2
from ..groups._se3 import SE3
from ._graph import BetweenFactors, PoseGraph, square_root_information

# tag -> (dimension, kind, number of fields after the tag)
_TAGS = {
    "VERTEX_SE2": (2, "vertex", 4),
    "EDGE_SE2": (2, "edge", 11),
    "VERTEX_SE3:QUAT": (3, "vertex", 8),
    "EDGE_SE3:QUAT": (3, "edge", 30),
    "FIX": (None, "fix", None),
}
_UNSUPPORTED = (
    "VERTEX_XY",
    "EDGE_SE2_XY",
    "VERTEX_TRACKXYZ",
    "EDGE_SE3_TRACKXYZ",
    "PARAMS_SE3OFFSET",
    "VERTEX_SE3:EXPMAP",
    "EDGE_SE3:EXPMAP",
    "VERTEX_POINTXYZ",
    "EDGE_SE3_POINTXYZ",
)


class G2oError(ValueError):
    """A g2o file that cannot be read; the message names the file and line."""


def _upper_to_symmetric(values, d):
    """A symmetric `(k, d, d)` matrix from `(k, d(d+1)/2)` row-major upper-triangle entries."""
    rows, cols = np.triu_indices(d)
    matrix = np.zeros((values.shape[0], d, d))
    matrix[:, rows, cols] = values
    matrix[:, cols, rows] = values
    return matrix


def read_g2o(path, *, dtype=None) -> PoseGraph:
    """Read a 2D or 3D g2o file into a `PoseGraph`.

    **Arguments:**
    - `path`: the file.
    - `dtype`: float dtype of the poses (default: JAX's default float; enable x64 for pose graphs).

    **Returns:** a `PoseGraph` whose poses are in the file's vertex order, with the file's ids in
    `vertex_ids`; edges become index pairs into the poses.

    **Raises:** `G2oError` (a `ValueError`) naming the line for a malformed line (wrong field
    count, a non-number, a non-unit-able quaternion), an unknown or unsupported tag, 2D and 3D
    mixed, a duplicate vertex id, an edge to a vertex that is not in the file, a self-loop, or an
    information matrix that is not symmetric positive definite; also for a file with no edges
    and no vertices, or one whose edges (without vertices) are not connected.
    """
    path = os.fspath(path)
    dim = None
    vertex_ids, vertex_values, vertex_lines = [], [], {}
    edge_pairs, edge_values, edge_lines = [], [], []
    fixed_ids = []
    with open(path) as handle:
        for number, line in enumerate(handle, start=1):
            fields = line.split()
            if not fields or fields[0].startswith("#"):
                continue
            tag = fields[0]
            where = f"{path}:{number}"
            if tag not in _TAGS:
                if tag in _UNSUPPORTED:
                    raise G2oError(
                        f"{where}: tag {tag!r} is not supported (pose graphs only: "
                        f"{', '.join(t for t in _TAGS)})."
                    )
                raise G2oError(f"{where}: unknown tag {tag!r}.")
            tag_dim, kind, count = _TAGS[tag]
            if kind == "fix":
                if len(fields) < 2:
                    raise G2oError(f"{where}: FIX needs at least one vertex id.")
                fixed_ids.extend(_ints(fields[1:], where))
                continue
            if dim is None:
                dim = tag_dim
            elif dim != tag_dim:
                raise G2oError(f"{where}: {tag} in a {dim}D file (2D and 3D elements mixed).")
            if len(fields) - 1 != count:
                raise G2oError(f"{where}: {tag} needs {count} fields, got {len(fields) - 1}.")
            if kind == "vertex":
                (vertex_id,) = _ints(fields[1:2], where)
                if vertex_id in vertex_lines:
                    raise G2oError(
                        f"{where}: vertex {vertex_id} already defined on line "
                        f"{vertex_lines[vertex_id]}."
                    )
                vertex_lines[vertex_id] = number
                vertex_ids.append(vertex_id)
                vertex_values.append(_floats(fields[2:], where))
            else:
                pair = _ints(fields[1:3], where)
                if pair[0] == pair[1]:
                    raise G2oError(f"{where}: edge joins vertex {pair[0]} to itself.")
                edge_pairs.append(pair)
                edge_values.append(_floats(fields[3:], where))
                edge_lines.append(number)
    if dim is None:
        raise G2oError(f"{path}: no vertices and no edges.")
    group = SE2 if dim == 2 else SE3
    d = group.tangent_dim
    edge_pairs = np.asarray(edge_pairs, dtype=np.int64).reshape(-1, 2)
    width = _TAGS["EDGE_SE2" if dim == 2 else "EDGE_SE3:QUAT"][2] - 2
    edge_values = np.asarray(edge_values, dtype=np.float64).reshape(len(edge_lines), width)
    edge_lines = np.asarray(edge_lines, dtype=np.int64)

    measured = _poses_from_rows(group, edge_values[:, : 3 if dim == 2 else 7], edge_lines, path)
    information = _upper_to_symmetric(edge_values[:, 3 if dim == 2 else 7 :], d)
    try:
        root = square_root_information(information, "information matrix of edge")
    except ValueError as error:
        index = int(str(error).split("edge ")[1].split(" ")[0])
        raise G2oError(
            f"{path}:{edge_lines[index]}: the information matrix is not symmetric "
            f"positive definite ({str(error).split('definite ')[1]})."
        ) from None

    if vertex_ids:
        ids = np.asarray(vertex_ids, dtype=np.int64)
        order = np.argsort(ids, kind="stable")
        sorted_ids = ids[order]
        found = np.searchsorted(sorted_ids, edge_pairs.clip(min=sorted_ids[0]))
        found = found.clip(max=len(ids) - 1)
        missing = sorted_ids[found] != edge_pairs
        if np.any(missing):
            row = int(np.argmax(np.any(missing, axis=1)))
            vertex = int(edge_pairs[row][np.argmax(missing[row])])
            raise G2oError(
                f"{path}:{edge_lines[row]}: edge refers to vertex {vertex}, which the "
                "file does not define."
            )
        index = order[found]
        rows = np.asarray(vertex_values, dtype=np.float64)
        lines = np.asarray([vertex_lines[v] for v in vertex_ids])
        poses = _poses_from_rows(group, rows, lines, path)
        has_vertices = True
    else:
        ids, index = np.unique(edge_pairs, return_inverse=True)
        index = index.reshape(-1, 2)
        has_vertices = False
    lookup = {int(v): k for k, v in enumerate(ids)}
    for vertex in fixed_ids:
        if vertex not in lookup:
            raise G2oError(
                f"{path}: FIX refers to vertex {vertex}, which the file does not define."
            )
    fixed = np.unique(np.asarray([lookup[v] for v in fixed_ids], dtype=np.int64))

    to_dtype = (lambda x: jnp.asarray(x)) if dtype is None else (lambda x: jnp.asarray(x, dtype))
    measured = group._wrap(to_dtype(measured))
    between = BetweenFactors(index[:, 0].copy(), index[:, 1].copy(), measured, to_dtype(root))
    if has_vertices:
        poses = group._wrap(to_dtype(poses))
    else:
        from ._init import spanning_tree_poses

        n = len(ids)
        placeholder = PoseGraph(group.identity((n,), dtype=measured.dtype), ids, between)
        count, _ = placeholder.components()
        if count > 1:
            raise G2oError(
                f"{path}: the file has no vertices and its edges form {count} "
                "disconnected components, so no initial poses can be composed."
            )
        poses = spanning_tree_poses(placeholder)
    return PoseGraph(poses, ids, between, fixed=fixed)


def _ints(fields, where):
    try:
        return [int(f) for f in fields]
    except ValueError:
        raise G2oError(f"{where}: expected integer ids, got {' '.join(fields)!r}.") from None


def _floats(fields, where):
    try:
        values = [float(f) for f in fields]
    except ValueError:
        bad = next(f for f in fields if not _is_float(f))
        raise G2oError(f"{where}: {bad!r} is not a number.") from None
    if not all(np.isfinite(values)):
        raise G2oError(f"{where}: non-finite value.")
    return values


def _is_float(text):
    try:
        float(text)
    except ValueError:
        return False
    return True


def _poses_from_rows(group, rows, lines, path):
    """Parameters `(k, parameters_dim)` from g2o rows: `x y θ` or `x y z qx qy qz qw`."""
    if group is SE2:
        x, y, theta = rows[:, 0], rows[:, 1], rows[:, 2]
        return np.stack([np.cos(theta), np.sin(theta), x, y], axis=1)
    xyzw = rows[:, 3:7]
    norm = np.linalg.norm(xyzw, axis=1)
    bad = ~(np.abs(norm - 1.0) < 1e-3)
    if np.any(bad):
        k = int(np.argmax(bad))
        raise G2oError(
            f"{path}:{lines[k]}: quaternion {xyzw[k].tolist()} is not unit (norm {norm[k]:.6g})."
        )
    wxyz = np.concatenate([xyzw[:, 3:], xyzw[:, :3]], axis=1) / norm[:, None]
    return np.concatenate([wxyz, rows[:, :3]], axis=1)


def write_g2o(path, graph: PoseGraph, *, poses=None):
    """Write `graph` (with `poses` in place of `graph.poses` if given, e.g. an optimized result)
    as a g2o file that `read_g2o` and GTSAM's `readG2o` read back: vertices in pose order with
    `graph.vertex_ids`, then edges, then a `FIX` line for fixed poses. Priors are not written
    (g2o has no prior tag)."""
    poses = graph.poses if poses is None else poses
    params = np.asarray(poses.parameters(), dtype=np.float64)
    ids = np.asarray(graph.vertex_ids)
    measured = np.asarray(graph.between.measured.parameters(), dtype=np.float64)
    root = np.asarray(graph.between.sqrt_information, dtype=np.float64)
    information = np.swapaxes(root, 1, 2) @ root
    d = root.shape[-1]
    rows, cols = np.triu_indices(d)
    upper = information[:, rows, cols]
    lines = []
    if graph.dim == 2:
        theta = np.arctan2(params[:, 1], params[:, 0])
        for v, p, t in zip(ids, params, theta):
            lines.append(f"VERTEX_SE2 {v} {p[2]:.17g} {p[3]:.17g} {t:.17g}")
        theta = np.arctan2(measured[:, 1], measured[:, 0])
        for a, b, z, t, info in zip(
            ids[graph.between.i], ids[graph.between.j], measured, theta, upper
        ):
            values = " ".join(f"{x:.17g}" for x in (z[2], z[3], t, *info))
            lines.append(f"EDGE_SE2 {a} {b} {values}")
    else:
        for v, p in zip(ids, params):
            values = " ".join(f"{x:.17g}" for x in (*p[4:], *p[1:4], p[0]))
            lines.append(f"VERTEX_SE3:QUAT {v} {values}")
        for a, b, z, info in zip(ids[graph.between.i], ids[graph.between.j], measured, upper):
            values = " ".join(f"{x:.17g}" for x in (*z[4:], *z[1:4], z[0], *info))
            lines.append(f"EDGE_SE3:QUAT {a} {b} {values}")
    if len(graph.fixed):
        lines.append("FIX " + " ".join(str(v) for v in ids[graph.fixed]))
    with open(os.fspath(path), "w") as handle:
        handle.write("\n".join(lines) + "\n")
