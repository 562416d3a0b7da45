r"""Reading and writing Bundler's `.out` files (Snavely's Bundler v0.3/v0.4, the output of its
structure from motion and the input of GTSAM's `SfmData.FromBundlerFile`).

Layout (Snavely, "Bundler: Structure from Motion for Unordered Image Collections", user manual,
"Output format"), one group of numbers per line:

| lines | fields |
|---|---|
| 1 | `# Bundle file v0.3` |
| 2 | `num_cameras num_points` |
| 5 per camera | `f k1 k2`, the three rows of $R$, `t` |
| 3 per point | position $X$, colour `r g b` (0-255), view list `n  camera key x y  …` |

Bundler's camera is the one BAL files hold ("Bundle Adjustment in the Large" took its problems
from Bundler and wrote its cameras with $R$ as a rotation vector; Agarwal et al. 2010's README
and Bundler's manual state the same model): $P = R X + t$, $p = -P_{xy}/P_z$ (the camera looks
down its $-z$ axis), $u = f\,(1 + k_1\|p\|^2 + k_2\|p\|^4)\,p$, pixels with the origin at the
image centre, $x$ to the right and $y$ **up**. So the conversion to a `BALProblem` keeps $t$,
$f$, $k_1$, $k_2$ and the observations as they are and turns $R$ into its rotation vector
$\mathrm{Log}(R)$; `lieax.ba.project` then reproduces the file's observations. (GTSAM, whose
cameras look down $+z$ with $y$ down, reads the same file as the pose $(R^\top R_x(\pi),
-R^\top t)$ and the pixel $(x, -y)$: `openGL2gtsam` in `gtsam/sfm/SfmData.cpp`.) `key` is the
index of the feature in its image's key file, kept in `keypoint_indices`.
"""

import dataclasses
import os

import numpy as np

from ._bal import BALError, BALProblem, checked_arrays
from ._synthetic import _rotation_matrices, _rotvecs

_HEADER = "# Bundle file v0.3"
# |R^T R - I| and |det R - 1| above this: not a rotation (files print R with 10 digits)
_ROTATION_TOLERANCE = 1e-6


@dataclasses.dataclass(frozen=True)
class BundlerProblem(BALProblem):
    """A `BALProblem` read from a Bundler file, with what Bundler adds per point and observation.

    **Fields** (besides `BALProblem`'s, observations ordered point by point as the file lists
    them):
    - `colors`: `(m, 3)` uint8 RGB of each point.
    - `keypoint_indices`: `(k,)` int64, each observation's feature index in its image.
    """

    colors: np.ndarray | None = None
    keypoint_indices: np.ndarray | None = None


def _numbers(fields, number, path, kind=float):
    try:
        return [kind(f) for f in fields]
    except ValueError:
        bad = next(f for f in fields if not _parses(f, kind))
        expected = "an integer" if kind is int else "a number"
        raise BALError(f"{path}:{number}: expected {expected}, got {bad!r}.") from None


def _parses(text, kind):
    try:
        kind(text)
    except ValueError:
        return False
    return True


def read_bundler(path: str | os.PathLike[str]) -> BundlerProblem:
    r"""Read a Bundler `.out` file as a `BALProblem` (see the module docstring for the layout and
    the camera conversion).

    **Returns:** a `BundlerProblem`: cameras `(n, 9)` (rotation vector of $R$, $t$, $f$, $k_1$,
    $k_2$), points, observations point by point, colours and keypoint indices.

    **Raises:** `BALError` (a `ValueError`) naming the file and line for a first line that is not
    `# Bundle file v…`, a counts line that is not two integers $\ge 0$, a line with the wrong
    number of fields, a word or non-finite value where a number belongs, a camera whose $R$ is
    not a rotation (an all-zero camera is one Bundler could not register: a `BALProblem` cannot
    hold it), a colour outside 0-255, a camera index out of range or a negative key, a file that
    ends early or has lines after the last point.
    """
    path = os.fspath(path)
    with open(path, encoding="latin-1") as handle:
        text = handle.read()
    numbered = [(n, line.split()) for n, line in enumerate(text.splitlines(), 1) if line.strip()]
    if not numbered or not " ".join(numbered[0][1]).startswith("# Bundle file v"):
        found = " ".join(numbered[0][1]) if numbered else "an empty file"
        raise BALError(f"{path}:1: expected the header {_HEADER!r}, found {found!r}.")
    position = 1

    def take(count, what):
        """The next non-blank line, with `count` fields."""
        nonlocal position
        if position >= len(numbered):
            last = numbered[-1][0]
            raise BALError(f"{path}:{last}: the file ends before {what}.")
        number, fields = numbered[position]
        position += 1
        if count is not None and len(fields) != count:
            raise BALError(f"{path}:{number}: {what} needs {count} fields, got {len(fields)}.")
        return number, fields

    number, fields = take(2, "'num_cameras num_points'")
    num_cameras, num_points = _numbers(fields, number, path, int)
    if num_cameras < 0 or num_points < 0:
        raise BALError(f"{path}:{number}: negative counts {num_cameras} {num_points}.")

    cameras = np.zeros((num_cameras, 9))
    for c in range(num_cameras):
        rows, lines = [], []
        for what in ("f k1 k2", "row 1 of R", "row 2 of R", "row 3 of R", "t"):
            number, fields = take(3, f"camera {c}'s {what}")
            rows.append(_numbers(fields, number, path))
            lines.append(number)
        block = np.asarray(rows)
        if not np.all(np.isfinite(block)):
            k = int(np.argmax(~np.all(np.isfinite(block), axis=1)))
            raise BALError(f"{path}:{lines[k]}: non-finite value in camera {c}.")
        R = block[1:4]
        if not np.any(R):
            raise BALError(
                f"{path}:{lines[1]}: camera {c} is all zeros (an image Bundler did not "
                "register), which a BALProblem cannot hold."
            )
        off = max(np.abs(R.T @ R - np.eye(3)).max(), abs(np.linalg.det(R) - 1))
        if off > _ROTATION_TOLERANCE:
            raise BALError(
                f"{path}:{lines[1]}: camera {c}'s R is not a rotation (|RᵀR - I|, |det R - 1| up "
                f"to {off:.3g})."
            )
        cameras[c, :3] = _rotvecs(R[None])[0]
        cameras[c, 3:6] = block[4]
        cameras[c, 6:] = block[0]

    points = np.zeros((num_points, 3))
    colors = np.zeros((num_points, 3), np.uint8)
    views, view_lines, point_of_view = [], [], []
    for p in range(num_points):
        number, fields = take(3, f"point {p}'s position")
        points[p] = _numbers(fields, number, path)
        if not np.all(np.isfinite(points[p])):
            raise BALError(f"{path}:{number}: non-finite value in point {p}'s position.")
        number, fields = take(3, f"point {p}'s colour")
        color = _numbers(fields, number, path, int)
        if min(color) < 0 or max(color) > 255:
            raise BALError(f"{path}:{number}: colour {color} outside 0-255.")
        colors[p] = color
        number, fields = take(None, f"point {p}'s view list")
        (count,) = _numbers(fields[:1], number, path, int)
        if count < 0 or len(fields) != 1 + 4 * count:
            raise BALError(
                f"{path}:{number}: a view list is 'n' then n × 'camera key x y' "
                f"({'1 + 4n' if count < 0 else 1 + 4 * count} fields), got {len(fields)} fields."
            )
        for k in range(count):
            camera, key = _numbers(fields[1 + 4 * k : 3 + 4 * k], number, path, int)
            if not 0 <= camera < num_cameras or key < 0:
                raise BALError(
                    f"{path}:{number}: view {k} has camera {camera} (of {num_cameras}) and key "
                    f"{key} (keys are >= 0)."
                )
            views.append((camera, key, *_numbers(fields[3 + 4 * k : 5 + 4 * k], number, path)))
        view_lines.extend([number] * count)
        point_of_view.extend([p] * count)
    if position < len(numbered):
        raise BALError(f"{path}:{numbered[position][0]}: lines after the last point.")
    table = np.asarray(views, np.float64).reshape(-1, 4)
    bad = ~np.all(np.isfinite(table), axis=1)
    if np.any(bad):
        raise BALError(f"{path}:{view_lines[np.argmax(bad)]}: non-finite value in a view.")
    return BundlerProblem(
        camera_indices=table[:, 0].astype(np.int64),
        point_indices=np.asarray(point_of_view, np.int64),
        observations=table[:, 2:].copy(),
        cameras=cameras,
        points=points,
        colors=colors,
        keypoint_indices=table[:, 1].astype(np.int64),
    )


def write_bundler(path: str | os.PathLike[str], problem: BALProblem) -> None:
    r"""Write `problem` (a `BALProblem`, e.g. read by `read_bal` or `read_bundler`) as a Bundler
    v0.3 file that `read_bundler` and GTSAM's `SfmData.FromBundlerFile` read: each camera's
    rotation vector as the matrix $R = \mathrm{Exp}(\omega)$, numbers with 17 significant digits
    (exact for float64, up to the rotation's round trip), observations grouped by point (in
    their order within a point). Colours and keys come from a `BundlerProblem`; other problems
    get white points and key 0.

    **Raises:** `ValueError` as `write_bal` for arrays of the wrong shape, indices out of range
    or non-finite values.
    """
    cameras, points, observations, camera_indices, point_indices = checked_arrays(problem)
    k = observations.shape[0]
    colors = getattr(problem, "colors", None)
    colors = np.full((len(points), 3), 255) if colors is None else np.asarray(colors)
    keys = getattr(problem, "keypoint_indices", None)
    keys = np.zeros(k, np.int64) if keys is None else np.asarray(keys, np.int64)

    def row(values):
        return " ".join(f"{v:.17g}" for v in values)

    lines = [_HEADER, f"{len(cameras)} {len(points)}"]
    rotations = _rotation_matrices(cameras[:, :3])
    for camera, R in zip(cameras, rotations):
        lines += [row(camera[6:]), *(row(r) for r in R), row(camera[3:6])]
    order = np.argsort(point_indices, kind="stable")
    starts = np.searchsorted(point_indices[order], np.arange(len(points) + 1))
    for p in range(len(points)):
        picked = order[starts[p] : starts[p + 1]]
        views = " ".join(
            f"{c} {key} {x:.17g} {y:.17g}"
            for c, key, (x, y) in zip(
                camera_indices[picked].tolist(), keys[picked].tolist(), observations[picked]
            )
        )
        color = " ".join(str(int(v)) for v in colors[p])
        lines += [row(points[p]), color, f"{len(picked)} {views}".rstrip()]
    with open(os.fspath(path), "w") as handle:
        handle.write("\n".join(lines) + "\n")
