"""What the point-cloud readers share: the cloud they return, the error they raise, and the
assembly of points, normals and colours from a file's per-point fields."""

from typing import NamedTuple

import numpy as np


class PointCloudData(NamedTuple):
    """A point cloud read from a file (NumPy arrays, one row per point).

    **Fields:**

    - `points`: `(n, 3)` float, x y z.
    - `normals`: `(n, 3)` float, or `None` when the file has none.
    - `colors`: `(n, 3)` float in `[0, 1]`, or `None`.
    - `fields`: every per-point property of the file by name, as read (`x`, `y`, `z`, `nx` or
      `normal_x`, `red`, `intensity`, ...).
    """

    points: np.ndarray
    normals: np.ndarray | None
    colors: np.ndarray | None
    fields: dict


class PointCloudFileError(ValueError):
    """A PLY or PCD file that cannot be read. The message names the file and where in it:
    `path:line: expected ..., found ...` for the header and ascii data, `path: byte N: ...` for
    binary data."""


def line_error(path, line, expected, found) -> PointCloudFileError:
    """The error for line `line` (1-based) of a text header or ascii body."""
    return PointCloudFileError(f"{path}:{line}: expected {expected}, found {found}.")


def byte_error(path, offset, message) -> PointCloudFileError:
    """The error for binary data at byte `offset` of the file."""
    return PointCloudFileError(f"{path}: byte {offset}: {message}.")


def header_lines(data):
    """`(line number, line, offset of the next line)` for each line of `data` (1-based; the
    newline is not part of the line, the last line may lack one)."""
    offset, number = 0, 0
    while offset < len(data):
        end = data.find(b"\n", offset)
        end = len(data) if end < 0 else end
        number += 1
        yield number, data[offset:end], end + 1
        offset = end + 1


def last_line(text, first_line) -> int:
    """The number of the last non-blank line of `text`, whose first line is `first_line`."""
    return first_line + text.rstrip().count(b"\n")


def shown(word, limit=40) -> str:
    """A word of a file as an error message quotes it (repr, cut to `limit` characters)."""
    if isinstance(word, bytes):
        word = word.decode("ascii", "replace")
    return repr(word if len(word) <= limit else word[:limit] + "...")


def assemble(fields, dtype) -> PointCloudData:
    """Points, normals (`nx ny nz` or `normal_x normal_y normal_z`) and colours (`red green blue`
    or `r g b` over 255, else a packed `rgb`/`rgba` as PCL stores it: $r$ in bits 16-23, $g$ in
    8-15, $b$ in 0-7 of a uint32, or of a float32's bit pattern) from a file's fields, which the
    reader has checked to hold `x`, `y`, `z`."""

    def pick(*options):
        for names in options:
            if all(name in fields for name in names):
                return np.stack([np.asarray(fields[name], np.float64) for name in names], axis=1)
        return None

    points = pick(("x", "y", "z"))
    normals = pick(("nx", "ny", "nz"), ("normal_x", "normal_y", "normal_z"))
    colors = pick(("red", "green", "blue"), ("r", "g", "b"))
    if colors is not None:
        colors = colors / 255.0
    elif "rgb" in fields or "rgba" in fields:
        packed = np.asarray(fields.get("rgb", fields.get("rgba")))
        bits = (
            packed.astype(np.float32).view(np.uint32)
            if packed.dtype.kind == "f"
            else packed.astype(np.uint32)
        )
        colors = np.stack([(bits >> 16) & 255, (bits >> 8) & 255, bits & 255], axis=1) / 255.0
    as_dtype = lambda a: None if a is None else a.astype(dtype)
    return PointCloudData(as_dtype(points), as_dtype(normals), as_dtype(colors), dict(fields))


def as_rows(array, what, count=None) -> np.ndarray:
    """`array` as float64 of shape `(n, 3)` (`(count, 3)` when given), or a `ValueError`."""
    array = np.asarray(array, np.float64)
    if array.ndim != 2 or array.shape[1] != 3:
        raise ValueError(f"{what} must have shape (n, 3), got {array.shape}.")
    if count is not None and len(array) != count:
        raise ValueError(f"{what} must have {count} rows (one per point), got {len(array)}.")
    return array
