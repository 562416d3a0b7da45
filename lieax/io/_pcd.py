"""PCD point clouds (ascii, binary, binary_compressed), after the Point Cloud Library's "PCD file
format" (v0.7; `binary_compressed` stores each field's column contiguously, LZF-compressed)."""

import io
import os
import warnings

import numpy as np
import numpy.typing as npt

from ._common import (
    PointCloudData,
    as_rows,
    assemble,
    byte_error,
    header_lines,
    line_error,
    shown,
)
from ._lzf import lzf_decompress

_PCD_TYPES = {("F", 4): "f4", ("F", 8): "f8", ("I", 1): "i1", ("I", 2): "i2", ("I", 4): "i4",
              ("I", 8): "i8", ("U", 1): "u1", ("U", 2): "u2", ("U", 4): "u4", ("U", 8): "u8"}  # fmt: skip
_SINGLE = ("x", "y", "z", "normal_x", "normal_y", "normal_z", "rgb", "rgba")
_MODES = ("ascii", "binary", "binary_compressed")


def read_pcd(path: str | os.PathLike[str], *, dtype: npt.DTypeLike = np.float64) -> PointCloudData:
    """Read a PCD file (v0.5 to v0.7).

    **Arguments:**

    - `path`: the file (DATA ascii, binary or binary_compressed; LF or CRLF header lines).
    - `dtype`: of `points`, `normals` and `colors`.

    **Returns:** a `PointCloudData` of `POINTS` points (`WIDTH`·`HEIGHT` when there is no
    `POINTS` line; `POINTS` wins when they differ, as in Open3D). Organized clouds (HEIGHT > 1)
    are flattened row by row and NaN points are kept, as Open3D does by default; `_` padding
    fields are dropped; a field of `COUNT` $k > 1$ is an `(n, k)` array in `fields`. `VIEWPOINT`
    is checked but not applied (the points stay in the sensor frame, as in PCL and Open3D).
    A packed `rgb`/`rgba` of TYPE F in ascii data may be written as the float whose bits are the
    colour (PCL < 1.8) or as those bits' unsigned integer (PCL >= 1.8): an integer value in
    $[0, 2^{32})$ is read as the latter (Open3D reads it as a float, so its colours are wrong).

    **Raises:** `PointCloudFileError` (a `ValueError`) naming the file and the line (header,
    ascii data) or byte (binary data): a malformed header line, FIELDS/SIZE/TYPE/COUNT of
    different lengths, neither `POINTS` nor `WIDTH`, no `x y z`, a word where a number should
    be, a row of the wrong length, data that ends early, corrupt `binary_compressed` data.
    """
    with open(path, "rb") as stream:
        data = stream.read()
    header, lines, offset, number = _header(data, path)
    names, kinds, counts, n = _layout(header, lines, path, number)
    mode = header["DATA"][0].lower()
    if mode == "ascii":
        raw = _read_ascii(data[offset:], names, kinds, counts, n, path, number + 1)
    elif mode == "binary":
        record = np.dtype([(f"f{i}", "<" + k, (c,)) for i, (k, c) in enumerate(zip(kinds, counts))])
        if len(data) - offset < record.itemsize * n:
            raise byte_error(
                path, offset,
                f"expected {n} points of {record.itemsize} bytes ({record.itemsize * n} bytes), "
                f"found the file ends after {len(data) - offset}",
            )  # fmt: skip
        table = np.frombuffer(data, record, n, offset)
        raw = [table[f"f{i}"] for i in range(len(names))]
    else:
        raw = _read_compressed(data, offset, kinds, counts, n, path)
    fields = {}
    for name, column, count in zip(names, raw, counts):
        if name != "_":
            column = np.asarray(column).reshape(n, count)
            fields[name] = column[:, 0] if count == 1 else column
    return assemble(fields, dtype)


def _header(data, path):
    """(keyword → words, keyword → line number, offset of the data, line number of DATA)."""
    header, lines, number = {}, {}, 0
    for number, line, offset in header_lines(data):
        words = line.decode("ascii", "replace").split()
        if not words or words[0].startswith("#"):
            continue
        keyword = words[0].upper()
        header[keyword], lines[keyword] = words[1:], number
        if keyword == "DATA":
            if len(words) != 2 or words[1].lower() not in _MODES:
                raise line_error(
                    path, number, "'DATA ascii|binary|binary_compressed'", shown(line.strip())
                )
            return header, lines, offset, number
    raise line_error(path, max(number, 1), "a 'DATA' line ending the header", "the end of the file")


def _layout(header, lines, path, data_line):
    """(names, NumPy type codes, counts, number of points) from the header, checked."""
    for required in ("FIELDS", "SIZE", "TYPE"):
        if required not in header:
            raise line_error(path, data_line, f"a {required} line before DATA", "none")
    names = header["FIELDS"]
    sizes = _values(header, "SIZE", lines, path)
    types = [t.upper() for t in header["TYPE"]]
    counts = _values(header, "COUNT", lines, path) if "COUNT" in header else [1] * len(names)
    for keyword, values in (("SIZE", sizes), ("TYPE", types), ("COUNT", counts)):
        if len(values) != len(names):
            raise line_error(
                path, lines.get(keyword, data_line),
                f"{len(names)} {keyword} entries (one per field of FIELDS)", len(values),
            )  # fmt: skip
    seen = set()
    for name, count in zip(names, counts):
        if name in seen and name != "_":
            raise line_error(path, lines["FIELDS"], "field names used once", f"{name!r} twice")
        seen.add(name)
        if name in _SINGLE and count != 1:
            raise line_error(path, lines["COUNT"], f"COUNT 1 for field {name!r}", count)
        if count < 1:
            raise line_error(path, lines["COUNT"], f"a COUNT >= 1 for field {name!r}", count)
    if not {"x", "y", "z"} <= seen:
        raise line_error(path, lines["FIELDS"], "fields x, y, z", ", ".join(names) or "none")
    kinds = []
    for name, size, kind in zip(names, sizes, types):
        if (kind, size) not in _PCD_TYPES:
            raise line_error(
                path, lines["TYPE"],
                f"a TYPE F (SIZE 4, 8), I or U (SIZE 1, 2, 4, 8) for field {name!r}",
                f"TYPE {kind} SIZE {size}",
            )  # fmt: skip
        kinds.append(_PCD_TYPES[(kind, size)])
    if "VIEWPOINT" in header:
        viewpoint = _values(header, "VIEWPOINT", lines, path, kind=float)
        if len(viewpoint) != 7:
            raise line_error(
                path, lines["VIEWPOINT"], "7 VIEWPOINT numbers (tx ty tz qw qx qy qz)",
                len(viewpoint),
            )  # fmt: skip
    width = _single(header, "WIDTH", lines, path)
    height = _single(header, "HEIGHT", lines, path)
    if "POINTS" in header:
        n = _single(header, "POINTS", lines, path)
    elif width is not None:
        n = width * (1 if height is None else height)
    else:
        raise line_error(path, data_line, "a POINTS or WIDTH line before DATA", "neither")
    return names, kinds, counts, n


def _values(header, keyword, lines, path, kind=int):
    values = []
    for word in header[keyword]:
        try:
            values.append(kind(word))
        except ValueError:
            expected = "an integer" if kind is int else "a number"
            raise line_error(
                path, lines[keyword], f"{expected} in {keyword}", shown(word)
            ) from None
    return values


def _single(header, keyword, lines, path):
    if keyword not in header:
        return None
    values = _values(header, keyword, lines, path)
    if len(values) != 1 or values[0] < 0:
        raise line_error(
            path, lines[keyword], f"one integer >= 0 after {keyword}", " ".join(header[keyword])
        )
    return values[0]


def _read_ascii(body, names, kinds, counts, n, path, first_line):
    """One point per non-blank line, read by NumPy's parser (line by line only to name the line
    at fault); `rgb`/`rgba` of TYPE F read as bits (see `_packed_colour`)."""
    width = sum(counts)
    text = body.decode("ascii", "replace")
    values = np.zeros((0, width)) if n == 0 else None
    if n:
        with warnings.catch_warnings():  # blank lines do not count towards max_rows (NumPy says so)
            warnings.filterwarnings("ignore", "Input line", UserWarning)
            try:
                values = np.loadtxt(
                    io.StringIO(text), np.float64, comments=None, ndmin=2, max_rows=n
                )
            except ValueError:
                pass
    if values is None or values.shape != (n, width):
        raise _ascii_error(text.split("\n"), width, n, path, first_line)
    raw, start = [], 0
    for name, kind, count in zip(names, kinds, counts):
        column = values[:, start : start + count]
        if name in ("rgb", "rgba") and kind == "f4":
            raw.append(_packed_colour(column[:, 0]))
        else:
            raw.append(column.astype(kind))
        start += count
    return raw


def _packed_colour(values):
    """A packed colour's float32 from its ascii value: an integer in $[0, 2^{32})$ is the uint32
    (PCL >= 1.8 writes rgb so), any other value the float whose bits are the colour (PCL < 1.8).
    (A float-written colour with an integer value would need an alpha of 75 to 79.)"""
    integer = (values == np.floor(values)) & (values >= 0) & (values < 2**32)
    bits = np.where(integer, values, 0).astype(np.uint32)
    float_bits = np.where(integer, 0, values).astype(np.float32).view(np.uint32)
    return np.where(integer, bits, float_bits).view(np.float32)


def _ascii_error(lines, width, n, path, first_line):
    """The error for ascii rows NumPy could not read: the first row of the wrong length or with a
    word that is not a number, else too few rows."""
    found, last = 0, first_line
    for number, line in enumerate(lines, start=first_line):
        words = line.split()
        if not words:
            continue
        last = number
        if len(words) != width:
            return line_error(
                path,
                number,
                f"{width} values in a point row",
                f"{len(words)}: {shown(line.strip())}",
            )
        for k, word in enumerate(words):
            try:
                float(word)
            except ValueError:
                return line_error(path, number, f"a number (value {k + 1} of the row)", shown(word))
        found += 1
        if found == n:
            return line_error(
                path, number, f"{n} rows of {width} numbers", "words NumPy cannot read"
            )
    return line_error(path, last, f"{n} point rows", f"the file ends after {found}")


def _read_compressed(data, offset, kinds, counts, n, path):
    """`binary_compressed`: two little-endian uint32 (compressed and uncompressed sizes), then
    LZF data that holds each field's column after the other."""
    if len(data) - offset < 8:
        raise byte_error(
            path, offset,
            "expected the 8-byte sizes of binary_compressed data, "
            f"found {len(data) - offset} bytes",
        )  # fmt: skip
    compressed, uncompressed = np.frombuffer(data, "<u4", 2, offset).tolist()
    point_size = sum(np.dtype(k).itemsize * c for k, c in zip(kinds, counts))
    if uncompressed != n * point_size:
        raise byte_error(
            path, offset + 4,
            f"expected an uncompressed size of {n * point_size} bytes ({n} points of "
            f"{point_size}), found {uncompressed}",
        )  # fmt: skip
    if len(data) - offset - 8 < compressed:
        raise byte_error(
            path, offset,
            f"expected {compressed} bytes of compressed data, found the file ends after "
            f"{len(data) - offset - 8}",
        )  # fmt: skip
    table = lzf_decompress(
        data[offset + 8 : offset + 8 + compressed], uncompressed, path, offset + 8
    )
    raw, start = [], 0
    for kind, count in zip(kinds, counts):
        width = np.dtype(kind).itemsize * count * n
        raw.append(np.frombuffer(table, "<" + kind, count * n, start).reshape(n, count))
        start += width
    return raw


def write_pcd(
    path: str | os.PathLike[str],
    points: npt.ArrayLike,
    normals: npt.ArrayLike | None = None,
    *,
    binary: bool = True,
) -> None:
    """Write points (and optional normals) as a PCD v0.7 file of float32 fields, DATA binary (or
    ascii with `binary=False`)."""
    points = as_rows(points, "points")
    names, values = ["x", "y", "z"], [points]
    if normals is not None:
        names += ["normal_x", "normal_y", "normal_z"]
        values.append(as_rows(normals, "normals", len(points)))
    table = np.concatenate(values, axis=1).astype("<f4")
    count = len(points)
    header = [
        "# .PCD v0.7 - Point Cloud Data file format (written by lieax)",
        "VERSION 0.7",
        "FIELDS " + " ".join(names),
        "SIZE " + " ".join(["4"] * len(names)),
        "TYPE " + " ".join(["F"] * len(names)),
        "COUNT " + " ".join(["1"] * len(names)),
        f"WIDTH {count}",
        "HEIGHT 1",
        "VIEWPOINT 0 0 0 1 0 0 0",
        f"POINTS {count}",
        f"DATA {'binary' if binary else 'ascii'}",
    ]
    with open(path, "wb") as stream:
        stream.write(("\n".join(header) + "\n").encode("ascii"))
        if binary:
            stream.write(table.tobytes())
        else:
            np.savetxt(stream, table, fmt="%.9g")
