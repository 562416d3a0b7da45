r"""Reading and writing g2o pose-graph files (2D `VERTEX_SE2`/`EDGE_SE2`, 3D
`VERTEX_SE3:QUAT`/`EDGE_SE3:QUAT`, and `FIX`).

Layouts (g2o's, as GTSAM's `readG2o`/`writeG2o` read and write them):

| line | fields |
|---|---|
| `VERTEX_SE2 id x y θ` | pose |
| `EDGE_SE2 i j x y θ I11 I12 I13 I22 I23 I33` | measurement $X_i^{-1}X_j$, upper triangle of $\Omega$ |
| `VERTEX_SE3:QUAT id x y z qx qy qz qw` | pose (quaternion scalar last) |
| `EDGE_SE3:QUAT i j x y z qx qy qz qw I11 … I16 I22 … I66` | 21 upper-triangle entries |
| `FIX id` | the vertex is held constant |

g2o orders the information of an SE3 edge as translation then rotation, like lieax's tangent
`(vx, vy, vz, ωx, ωy, ωz)` (GTSAM, whose tangent is rotation first, swaps the blocks on reading):
the matrix is used as read. The residual it weighs is lieax's $\mathrm{Log}(Z^{-1}X_i^{-1}X_j)$,
GTSAM's `BetweenFactor` error, so costs agree with GTSAM's.

Files that have edges but no vertices get initial poses by composing the measurements along a
breadth-first spanning tree from the smallest id (`lieax.graph.spanning_tree_poses`).

What the reader accepts, with GTSAM's `readG2o` as the reference: lines split on `\n` (a
trailing `\r` is whitespace, so Windows files read), fields on spaces and tabs, `#` to the end of a
line is a comment, a UTF-8 byte-order mark is skipped and the bytes are decoded as Latin-1 (so
comment bytes in any encoding read; tags and numbers are ASCII). Negative ids are ids (GTSAM reads
them too, as wrapped unsigned keys). Tags lieax does not model (landmarks `VERTEX_XY`/`EDGE_SE2_XY`,
`TUTORIAL_PARAMS_SE2`, other vertex and edge types) are skipped with one `G2oWarning` counting each.
Quaternions are normalised (a warning above a tolerance); information matrices that are not positive
definite are repaired by a documented policy (`read_g2o`'s `information`). Where GTSAM reads
silently what is wrong (too few fields read as zeros, extra fields ignored, an edge to a vertex
the file does not define, a self-loop, `-inf`), the reader refuses with `G2oError` naming the file
and line.
"""

import collections
import os
import warnings
from typing import NamedTuple

import numpy as np

from .._checks import to_device
from ..groups import SE2, SE3, kernels
from ._graph import BetweenFactors, PoseGraph, square_root_information

# tag -> (dimension, kind, number of fields after the tag)
_TAGS = {
    "VERTEX_SE2": (2, "vertex", 4),
    "EDGE_SE2": (2, "edge", 11),
    "VERTEX_SE3:QUAT": (3, "vertex", 8),
    "EDGE_SE3:QUAT": (3, "edge", 30),
    "FIX": (None, "fix", None),
}
_BOM = "\xef\xbb\xbf"  # the UTF-8 byte-order mark, decoded as Latin-1
_UTF16_BOMS = ("\xff\xfe", "\xfe\xff")
_LISTED_TAGS = 10  # the skipped-tags warning lists this many, in the order first seen
_INT64 = 2**63
# |‖q‖ - 1| above this warns (quaternions are always normalised); below _QUATERNION_MIN_NORM the
# quaternion has no direction and is refused.
_QUATERNION_TOLERANCE = 1e-3
_QUATERNION_MIN_NORM = 1e-6
# An information matrix with λ_min <= _NOT_PD * λ_max is not positive definite to working
# precision; a repair raises its eigenvalues (or diagonal) to at least _FLOOR * λ_max.
_NOT_PD = 1e-12
_FLOOR = 1e-9
_POLICIES = ("nearest", "diagonal", "raise")


class G2oError(ValueError):
    """A g2o file that cannot be read; the message names the file and line."""


class G2oWarning(UserWarning):
    """A g2o file read with lines skipped or values repaired; the message says which and how many."""


def _upper_to_symmetric(values, d):
    """A symmetric `(k, d, d)` matrix from `(k, d(d+1)/2)` row-major upper-triangle entries."""
    rows, cols = np.triu_indices(d)
    matrix = np.zeros((values.shape[0], d, d))
    matrix[:, rows, cols] = values
    matrix[:, cols, rows] = values
    return matrix


def read_g2o(path, *, information="nearest", dtype=None) -> PoseGraph:
    r"""Read a 2D or 3D g2o file into a `PoseGraph`.

    **Arguments:**

    - `path`: the file.
    - `information`: what to do with an edge whose information matrix $\Omega$ is not positive
      definite to working precision ($\lambda_{\min} \le 10^{-12}\lambda_{\max}$; public sets
      such as SE-Sync's `cubicle` and `rim` have thousands, which GTSAM reads as they are):
      - `"nearest"` (default): eigenvalue clipping, $\Omega' = V\,\mathrm{diag}(\max(\lambda_k,
        \delta))\,V^\top$ with $\Omega = V\mathrm{diag}(\lambda)V^\top$ and the floor
        $\delta = 10^{-9}\lambda_{\max}$: the nearest symmetric matrix in the Frobenius norm
        whose eigenvalues are all at least $\delta$ (Higham 1988, "Computing a nearest symmetric
        positive semidefinite matrix", Linear Algebra Appl. 103:103-118, applied to
        $\Omega - \delta I$); only the edges found not positive definite are changed;
      - `"diagonal"`: $\Omega' = \mathrm{diag}(\max(\Omega_{kk}, 10^{-9}\max_l \Omega_{ll}))$,
        the off-diagonal correlations dropped;
      - `"raise"`: refuse the file (`G2oError` naming the first such line).

      A repair warns once per file (`G2oWarning`) with the number of edges repaired, how, and the
      first line; a matrix with no positive eigenvalue (or diagonal entry) cannot be repaired and
      is refused.
    - `dtype`: float dtype of the poses (default: JAX's default float; enable x64 for pose graphs).

    **Returns:** a `PoseGraph` whose poses are in the file's vertex order, with the file's ids in
    `vertex_ids`; edges become index pairs into the poses.

    **Warns:** `G2oWarning` (once each, with counts and the first line) for skipped tags, for
    quaternions whose norm is off 1 by more than $10^{-3}$ (all quaternions are normalised), and
    for repaired information matrices.

    **Raises:** `G2oError` (a `ValueError`) naming the file and line for a malformed line (wrong
    field count, a word or a non-finite number where a number belongs, an id that is not an
    integer or beyond int64, a quaternion of norm below $10^{-6}$), 2D and 3D mixed, a duplicate
    vertex id, an edge or a `FIX` naming a vertex the file does not define (when it defines any),
    a self-loop, or an information matrix the `information` policy refuses; also for a file with
    no pose-graph vertices or edges, or one whose edges (without vertices) are not connected.
    """
    if information not in _POLICIES:
        raise ValueError(f"information must be one of {_POLICIES}, got {information!r}.")
    path = os.fspath(path)
    records = _read_records(path)
    dim, skipped = records.dim, records.skipped
    vertex_ids, vertex_values, vertex_lines = (
        records.vertex_ids, records.vertex_values, records.vertex_lines
    )  # fmt: skip
    edge_pairs, edge_values, edge_lines = (
        records.edge_pairs, records.edge_values, records.edge_lines
    )  # fmt: skip
    fixed_ids = records.fixed_ids
    _report_skipped(dim, skipped, path)
    group = SE2 if dim == 2 else SE3
    d = group.tangent_dim
    edge_pairs = np.asarray(edge_pairs, dtype=np.int64).reshape(-1, 2)
    width = _TAGS["EDGE_SE2" if dim == 2 else "EDGE_SE3:QUAT"][2] - 2
    edge_values = np.asarray(edge_values, dtype=np.float64).reshape(len(edge_lines), width)
    edge_lines = np.asarray(edge_lines, dtype=np.int64)
    _check_finite(edge_values, edge_lines, path)
    vertex_rows = np.asarray(vertex_values, dtype=np.float64).reshape(-1, 3 if dim == 2 else 7)
    vertex_lines_array = np.asarray([vertex_lines[v] for v in vertex_ids], dtype=np.int64)
    _check_finite(vertex_rows, vertex_lines_array, path)

    measured, measured_off = _poses_from_rows(
        group, edge_values[:, : 3 if dim == 2 else 7], edge_lines, path
    )
    upper = edge_values[:, 3 if dim == 2 else 7 :]
    root = square_root_information(
        _repaired_information(_upper_to_symmetric(upper, d), information, edge_lines, path),
        "information matrix of edge",
    )

    if vertex_ids:
        ids, index = _vertex_index(vertex_ids, edge_pairs, edge_lines, path)
        poses, poses_off = _poses_from_rows(group, vertex_rows, vertex_lines_array, path)
        has_vertices = True
    else:
        ids, index = np.unique(edge_pairs, return_inverse=True)
        index = index.reshape(-1, 2)
        poses_off = np.zeros(0)
        has_vertices = False
    _warn_quaternions(
        np.concatenate([poses_off, measured_off]),
        np.concatenate([vertex_lines_array, edge_lines]),
        path,
    )
    fixed = _fixed_index(fixed_ids, ids, path)

    # one transfer per array: `jnp.asarray` would compile a conversion per shape (issue 30)
    to_dtype = (
        (lambda x: to_device(x)) if dtype is None else (lambda x: to_device(np.asarray(x, dtype)))
    )
    measured = kernels.element(group, to_dtype(measured))
    between = BetweenFactors(index[:, 0].copy(), index[:, 1].copy(), measured, to_dtype(root))
    if has_vertices:
        poses = kernels.element(group, to_dtype(poses))
    else:
        poses = _composed_poses(group, ids, between, path)
    return PoseGraph(poses, ids, between, fixed=fixed)


def _report_skipped(dim, skipped, path):
    """One `G2oWarning` counting the lines of each skipped tag (`skipped`), and a `G2oError`
    for a file with no pose-graph element (`dim` None)."""
    if skipped:
        counts = list(skipped.items())
        listed = ", ".join(f"{tag!r} ×{n}" for tag, n in counts[:_LISTED_TAGS])
        if len(counts) > _LISTED_TAGS:
            listed += f" and {len(counts) - _LISTED_TAGS} other tags"
        warnings.warn(
            f"{path}: skipped {sum(skipped.values())} lines with tags lieax does not read "
            f"({listed}); read_g2o reads pose graphs ({', '.join(_TAGS)}).",
            G2oWarning,
            stacklevel=3,
        )
    if dim is None:
        raise G2oError(
            f"{path}: no pose-graph vertices or edges"
            + (
                f" (only skipped tags: {', '.join(list(skipped)[:_LISTED_TAGS])})."
                if skipped
                else "."
            )
        )


def _fixed_index(fixed_ids, ids, path):
    """The sorted positions in `ids` of the `FIX` lines' vertices (`(vertex id, line number)`
    pairs); a `G2oError` names the line of one the file does not define."""
    lookup = {int(v): k for k, v in enumerate(ids)}
    for vertex, number in fixed_ids:
        if vertex not in lookup:
            raise G2oError(
                f"{path}:{number}: FIX refers to vertex {vertex}, which the file does not define."
            )
    return np.unique(np.asarray([lookup[v] for v, _ in fixed_ids], dtype=np.int64))


def _composed_poses(group, ids, between, path):
    """Initial poses for a file with edges but no vertices: the measurements composed along a
    breadth-first spanning tree (`lieax.graph.spanning_tree_poses`); a `G2oError` when the
    edges are not connected."""
    from ._init import spanning_tree_poses

    n = len(ids)
    placeholder = PoseGraph(group.identity((n,), dtype=between.measured.dtype), ids, between)
    count, _ = placeholder.components()
    if count > 1:
        raise G2oError(
            f"{path}: the file has no vertices and its edges form {count} "
            "disconnected components, so no initial poses can be composed."
        )
    return spanning_tree_poses(placeholder)


def _vertex_index(vertex_ids, edge_pairs, edge_lines, path):
    """`(ids, index)`: the vertex ids as an array, and each edge's two positions in it (a
    `G2oError` names the line of an edge whose vertex the file does not define)."""
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
    return ids, order[found]


class _Records(NamedTuple):
    """The pose-graph lines of a g2o file, as read (`_read_records`)."""

    dim: object  # 2, 3, or None when the file has no pose-graph element
    vertex_ids: list
    vertex_values: list
    vertex_lines: dict  # vertex id -> line number
    edge_pairs: list
    edge_values: list
    edge_lines: list
    fixed_ids: list  # (vertex id, line number) of FIX lines
    skipped: collections.Counter  # lines of other tags, by tag


def _read_records(path):
    """The `_Records` of the g2o file `path`: each line's tag, ids and numbers checked (a
    `G2oError` names the line), nothing converted yet."""
    dim = None
    vertex_ids, vertex_values, vertex_lines = [], [], {}
    edge_pairs, edge_values, edge_lines = [], [], []
    fixed_ids = []
    skipped = collections.Counter()
    with open(path, encoding="latin-1", newline="\n") as handle:
        for number, line in enumerate(handle, start=1):
            if number == 1 and line.startswith(_BOM):
                line = line[len(_BOM) :]
            elif number == 1 and line.startswith(_UTF16_BOMS):
                raise G2oError(
                    f"{path}:1: the file is UTF-16 (byte-order mark); g2o is ASCII text."
                )
            if "#" in line:
                line = line[: line.index("#")]
            fields = line.split()
            if not fields:
                continue
            tag = fields[0]
            where = f"{path}:{number}"
            if tag not in _TAGS:
                skipped[tag] += 1
                continue
            tag_dim, kind, count = _TAGS[tag]
            if kind == "fix":
                if len(fields) < 2:
                    raise G2oError(f"{where}: FIX needs at least one vertex id.")
                fixed_ids.extend((vertex, number) for vertex in _ints(fields[1:], where))
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
    return _Records(
        dim, vertex_ids, vertex_values, vertex_lines, edge_pairs, edge_values, edge_lines,
        fixed_ids, skipped,
    )  # fmt: skip


def _ints(fields, where):
    try:
        ids = [int(f) for f in fields]
    except ValueError:
        bad = next(f for f in fields if not _is_int(f))
        raise G2oError(f"{where}: expected an integer vertex id, got {bad!r}.") from None
    for vertex in ids:
        if not -_INT64 <= vertex < _INT64:
            raise G2oError(f"{where}: vertex id {vertex} is outside the int64 range.")
    return ids


def _is_int(text):
    try:
        int(text)
    except ValueError:
        return False
    return True


def _floats(fields, where):
    try:
        return [float(f) for f in fields]
    except ValueError:
        bad = next(f for f in fields if not _is_float(f))
        raise G2oError(f"{where}: expected a number, got {bad!r}.") from None


def _is_float(text):
    try:
        float(text)
    except ValueError:
        return False
    return True


def _check_finite(rows, lines, path):
    """Refuse the first row (its line) holding a NaN or an infinity."""
    finite = np.isfinite(rows)
    if not np.all(finite):
        k = int(np.argmax(~np.all(finite, axis=1)))
        value = rows[k, int(np.argmax(~finite[k]))]
        raise G2oError(f"{path}:{lines[k]}: non-finite value {value} where a number belongs.")


def _repaired_information(information, policy, lines, path):
    """`information` `(m, d, d)` with the matrices that are not positive definite repaired by
    `policy` (see `read_g2o`), warning once with their count."""
    eigenvalues = np.linalg.eigvalsh(information)
    largest = eigenvalues[:, -1]
    bad = eigenvalues[:, 0] <= _NOT_PD * largest
    if not np.any(bad):
        return information
    first = int(np.argmax(bad))
    where = f"{path}:{lines[first]}"
    if policy == "raise":
        raise G2oError(
            f"{where}: the information matrix is not positive definite (eigenvalues "
            f"{np.array2string(eigenvalues[first], precision=3)}; information='nearest' or "
            "'diagonal' repairs it)."
        )
    broken = information[bad]
    if policy == "nearest":
        scale = largest[bad]
        what = "the eigenvalues of"
    else:
        diagonal = np.diagonal(broken, axis1=1, axis2=2)
        scale = diagonal.max(axis=1)
        what = "the diagonal entries of"
    if np.any(scale <= 0):
        k = int(np.flatnonzero(bad)[np.argmax(scale <= 0)])
        raise G2oError(
            f"{path}:{lines[k]}: the information matrix has no positive "
            f"{'eigenvalue' if policy == 'nearest' else 'diagonal entry'}, so there is nothing "
            f"to repair it from (eigenvalues {np.array2string(eigenvalues[k], precision=3)})."
        )
    floor = _FLOOR * scale[:, None]
    if policy == "nearest":
        values, vectors = np.linalg.eigh(broken)
        repaired = (vectors * np.maximum(values, floor)[:, None, :]) @ np.swapaxes(vectors, 1, 2)
        repaired = 0.5 * (repaired + np.swapaxes(repaired, 1, 2))
    else:
        repaired = np.zeros_like(broken)
        rows = np.arange(broken.shape[-1])
        repaired[:, rows, rows] = np.maximum(diagonal, floor)
    information = information.copy()
    information[bad] = repaired
    warnings.warn(
        f"{where}: {int(bad.sum())} of {len(bad)} edges have an information matrix that is not "
        f"positive definite (this line is the first); information={policy!r} raised {what} each "
        f"to at least {_FLOOR:g} times its largest. Pass information='raise' to refuse the file.",
        G2oWarning,
        stacklevel=3,
    )
    return information


def _warn_quaternions(off, lines, path):
    """Warn once if any quaternion's norm was off 1 by more than the tolerance."""
    far = off > _QUATERNION_TOLERANCE
    if np.any(far):
        first = int(np.argmin(np.where(far, lines, np.iinfo(np.int64).max)))
        warnings.warn(
            f"{path}:{lines[first]}: normalised {int(far.sum())} quaternions whose norm was off 1 "
            f"by more than {_QUATERNION_TOLERANCE:g} (at most {off.max():.3g}; this line is the "
            "first).",
            G2oWarning,
            stacklevel=3,
        )


def _poses_from_rows(group, rows, lines, path):
    r"""Parameters `(k, parameters_dim)` from g2o rows `x y θ` or `x y z qx qy qz qw` (the
    quaternion normalised), and each row's $|\lVert q\rVert - 1|$ (zeros for SE2)."""
    if group is SE2:
        x, y, theta = rows[:, 0], rows[:, 1], rows[:, 2]
        return np.stack([np.cos(theta), np.sin(theta), x, y], axis=1), np.zeros(len(rows))
    xyzw = rows[:, 3:7]
    norm = np.linalg.norm(xyzw, axis=1)
    bad = norm < _QUATERNION_MIN_NORM
    if np.any(bad):
        k = int(np.argmax(bad))
        raise G2oError(
            f"{path}:{lines[k]}: quaternion {xyzw[k].tolist()} has norm {norm[k]:.3g}, below "
            f"{_QUATERNION_MIN_NORM:g}: it has no rotation to normalise to."
        )
    wxyz = np.concatenate([xyzw[:, 3:], xyzw[:, :3]], axis=1) / norm[:, None]
    return np.concatenate([wxyz, rows[:, :3]], axis=1), np.abs(norm - 1.0)


def write_g2o(path, graph: PoseGraph, *, poses=None):
    r"""Write `graph` (with `poses` in place of `graph.poses` if given, e.g. an optimized result)
    as a g2o file that `read_g2o` and GTSAM's `readG2o` read back: vertices in pose order with
    `graph.vertex_ids` (negative ones too), then edges with the information $R^\top R$ as read
    (repaired, if `read_g2o` repaired it), then a `FIX` line for fixed poses. Priors are not
    written (g2o has no prior tag)."""
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
