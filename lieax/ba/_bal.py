"""Reading and writing "Bundle Adjustment in the Large" files (`problem-*.txt`, Agarwal et al.
2010, https://grail.cs.washington.edu/projects/bal/), plain or bz2-compressed (as they ship).

Layout, whitespace-separated:

| lines | fields |
|---|---|
| 1 | `num_cameras num_points num_observations` |
| next `num_observations` | `camera_index point_index x y` (pixels, origin at the image centre) |
| the rest | 9 per camera (rotation vector, translation, $f$, $k_1$, $k_2$), then 3 per point |

The camera and point numbers may be laid out one per line (as the dataset's files) or several
per line; `write_bal` writes one per line with `%.16e`, which round-trips float64 exactly. The
camera model is in `lieax.ba.project`.
"""

import bz2
import dataclasses
import os
from typing import TYPE_CHECKING, Self

import numpy as np
import numpy.typing as npt

if TYPE_CHECKING:  # this module reads and writes files with NumPy alone
    import jax

    from ..groups import SE3


class BALError(ValueError):
    """A BAL file that cannot be read; the message names the file and line."""


@dataclasses.dataclass(frozen=True)
class BALProblem:
    """A bundle-adjustment problem as a BAL file holds it (NumPy arrays, float64).

    **Fields:**

    - `camera_indices`, `point_indices`: `(k,)` int64, the camera and point of each observation.
    - `observations`: `(k, 2)` observed pixels.
    - `cameras`: `(n, 9)` rotation vector, translation, $f$, $k_1$, $k_2$ per camera.
    - `points`: `(m, 3)` world points.
    """

    camera_indices: np.ndarray
    point_indices: np.ndarray
    observations: np.ndarray
    cameras: np.ndarray
    points: np.ndarray

    @property
    def num_cameras(self) -> int:
        return self.cameras.shape[0]

    @property
    def num_points(self) -> int:
        return self.points.shape[0]

    @property
    def num_observations(self) -> int:
        return self.observations.shape[0]

    def camera_variables(self, dtype: npt.DTypeLike | None = None) -> "tuple[SE3, jax.Array]":
        """`(T_camera_world, intrinsics)`: the cameras as one batched `lieax.SE3` and `(n, 3)`
        intrinsics $(f, k_1, k_2)$ (see `lieax.ba.bal_to_camera`), in `dtype` (default: JAX's
        default float; enable x64 for bundle adjustment)."""
        import jax

        from ._camera import bal_to_camera

        dtype = jax.dtypes.canonicalize_dtype(float if dtype is None else dtype)
        return bal_to_camera(np.asarray(self.cameras, dtype))

    def with_parameters(self, cameras: npt.ArrayLike, points: npt.ArrayLike) -> Self:
        """The same observations with other `(n, 9)` cameras and `(m, 3)` points."""
        cameras = np.asarray(cameras, dtype=np.float64)
        points = np.asarray(points, dtype=np.float64)
        if cameras.shape != self.cameras.shape or points.shape != self.points.shape:
            raise ValueError(
                f"cameras and points must have shapes {self.cameras.shape} and "
                f"{self.points.shape}, got {cameras.shape} and {points.shape}."
            )
        return dataclasses.replace(self, cameras=cameras, points=points)


def _open(path, mode):
    if path.endswith(".bz2"):
        return bz2.open(path, mode)
    return open(path, mode)


def _numbers(tokens, line_of, where):
    """`tokens` as float64, or a `BALError` naming the line of the first bad one."""
    try:
        values = np.asarray(tokens, dtype=np.float64)
    except ValueError:
        for index, token in enumerate(tokens):
            try:
                float(token)
            except ValueError:
                raise BALError(f"{where}:{line_of(index)}: {token!r} is not a number.") from None
        raise
    bad = ~np.isfinite(values)
    if np.any(bad):
        index = int(np.argmax(bad))
        raise BALError(f"{where}:{line_of(index)}: non-finite value {tokens[index]!r}.")
    return values


def read_bal(path: str | os.PathLike[str]) -> BALProblem:
    """Read a BAL problem file (`.bz2` files are decompressed on the fly).

    **Arguments:**

    - `path`: the file.

    **Returns:** a `BALProblem`.

    **Raises:** `BALError` (a `ValueError`) naming the file and line for a header that is not
    three positive integers, an observation line without exactly four fields, a non-number, a
    non-finite value (NaN, inf), a camera or point index that is not an integer or is out of
    range, a file that ends before all camera and point values, or extra values after them.
    """
    path = os.fspath(path)
    try:
        with _open(path, "rt") as handle:
            text = handle.read()
    except (OSError, EOFError, UnicodeDecodeError) as error:
        if isinstance(error, FileNotFoundError):
            raise
        raise BALError(f"{path}: cannot be read ({error}).") from None
    lines = text.splitlines()
    # line numbers (1-based) of the non-blank lines
    numbered = [(number, line) for number, line in enumerate(lines, start=1) if line.strip()]
    if not numbered:
        raise BALError(f"{path}: the file is empty.")

    header_line, header = numbered[0]
    fields = header.split()
    if len(fields) != 3 or not all(f.isdigit() and int(f) > 0 for f in fields):
        raise BALError(
            f"{path}:{header_line}: the header must be three positive integers "
            f"'num_cameras num_points num_observations', got {header.strip()!r}."
        )
    num_cameras, num_points, num_observations = (int(f) for f in fields)

    observed = numbered[1 : 1 + num_observations]
    if len(observed) < num_observations:
        last = numbered[-1][0]
        raise BALError(
            f"{path}:{last}: the file ends after {len(observed)} of {num_observations} "
            "observation lines."
        )
    tokens = []
    for number, line in observed:
        row = line.split()
        if len(row) != 4:
            raise BALError(
                f"{path}:{number}: an observation needs 4 fields "
                f"'camera_index point_index x y', got {len(row)}."
            )
        tokens.extend(row)
    values = _numbers(tokens, lambda i: observed[i // 4][0], path).reshape(-1, 4)
    for column, (name, count) in enumerate((("camera", num_cameras), ("point", num_points))):
        index = values[:, column]
        bad = (index != np.round(index)) | (index < 0) | (index >= count)
        if np.any(bad):
            row = int(np.argmax(bad))
            raise BALError(
                f"{path}:{observed[row][0]}: {name} index {tokens[4 * row + column]!r} is not "
                f"an integer in [0, {count})."
            )

    rest = numbered[1 + num_observations :]
    expected = 9 * num_cameras + 3 * num_points
    rest_tokens = [token for _, line in rest for token in line.split()]

    def line_of(index):
        """The line of the `index`-th camera or point value."""
        counts = np.cumsum([len(line.split()) for _, line in rest])
        return rest[int(np.searchsorted(counts, index, side="right"))][0]

    if len(rest_tokens) < expected:
        last = rest[-1][0] if rest else observed[-1][0]
        raise BALError(
            f"{path}:{last}: the file ends after {len(rest_tokens)} of the {expected} "
            f"camera and point values ({num_cameras} × 9 + {num_points} × 3)."
        )
    if len(rest_tokens) > expected:
        raise BALError(
            f"{path}:{line_of(expected)}: values after the {expected} camera and point values "
            f"({num_cameras} × 9 + {num_points} × 3)."
        )

    parameters = _numbers(rest_tokens, line_of, path)
    return BALProblem(
        camera_indices=values[:, 0].astype(np.int64),
        point_indices=values[:, 1].astype(np.int64),
        observations=values[:, 2:].copy(),
        cameras=parameters[: 9 * num_cameras].reshape(num_cameras, 9),
        points=parameters[9 * num_cameras :].reshape(num_points, 3),
    )


def checked_arrays(problem):
    """`(cameras, points, observations, camera_indices, point_indices)` of a `BALProblem` as
    NumPy arrays (float64, int64), checked as a file writer needs them: `ValueError` for arrays
    of the wrong shape, non-finite values or indices out of range (a reader would reject the
    file)."""
    cameras = np.asarray(problem.cameras, dtype=np.float64)
    points = np.asarray(problem.points, dtype=np.float64)
    observations = np.asarray(problem.observations, dtype=np.float64)
    camera_indices = np.asarray(problem.camera_indices, np.int64)
    point_indices = np.asarray(problem.point_indices, np.int64)
    k = observations.shape[0]
    if (
        cameras.ndim != 2
        or cameras.shape[1] != 9
        or points.ndim != 2
        or points.shape[1] != 3
        or observations.shape != (k, 2)
        or camera_indices.shape != (k,)
        or point_indices.shape != (k,)
    ):
        raise ValueError(
            "a BAL problem needs cameras (n, 9), points (m, 3), observations (k, 2) and (k,) "
            f"indices, got {cameras.shape}, {points.shape}, {observations.shape}, "
            f"{camera_indices.shape} and {point_indices.shape}."
        )
    if not all(np.all(np.isfinite(a)) for a in (cameras, points, observations)):
        raise ValueError("a BAL problem's cameras, points and observations must be finite.")
    for name, index, count in (
        ("camera", camera_indices, cameras.shape[0]),
        ("point", point_indices, points.shape[0]),
    ):
        if k and (index.min() < 0 or index.max() >= count):
            raise ValueError(f"{name} indices must lie in [0, {count}).")
    return cameras, points, observations, camera_indices, point_indices


def write_bal(path: str | os.PathLike[str], problem: BALProblem) -> None:
    """Write `problem` as a BAL file (bz2-compressed when `path` ends with `.bz2`), every number
    with `%.16e` (exact for float64), cameras and points one value per line as the dataset does.

    **Raises:** `ValueError` for arrays of the wrong shape, indices out of range or non-finite
    values (the reader would reject the file).
    """
    path = os.fspath(path)
    cameras, points, observations, camera_indices, point_indices = checked_arrays(problem)
    k = observations.shape[0]
    table = np.column_stack([camera_indices, point_indices]).astype(np.int64)
    lines = [f"{cameras.shape[0]} {points.shape[0]} {k}"]
    lines += [
        f"{c} {p} {x:.16e} {y:.16e}"
        for (c, p), (x, y) in zip(table.tolist(), observations.tolist())
    ]
    lines += [f"{value:.16e}" for value in cameras.ravel().tolist()]
    lines += [f"{value:.16e}" for value in points.ravel().tolist()]
    with _open(path, "wt") as handle:
        handle.write("\n".join(lines) + "\n")
