"""PLY point clouds (ascii, binary little and big endian), after Greg Turk's specification
(Stanford, 1994) as Open3D (rply) and MeshLab read and write it."""

import os
import re

import numpy as np
import numpy.typing as npt

from ._common import (
    PointCloudData,
    as_rows,
    assemble,
    byte_error,
    header_lines,
    last_line,
    line_error,
    shown,
)

_PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1",
    "short": "i2", "int16": "i2", "ushort": "u2", "uint16": "u2",
    "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}  # fmt: skip
_FORMATS = ("ascii", "binary_little_endian", "binary_big_endian")


def read_ply(path: str | os.PathLike[str], *, dtype: npt.DTypeLike = np.float64) -> PointCloudData:
    """Read the `vertex` element of a PLY file.

    **Arguments:**

    - `path`: the file (ascii, binary_little_endian or binary_big_endian; LF or CRLF lines).
    - `dtype`: of `points`, `normals` and `colors`.

    **Returns:** a `PointCloudData` of the vertices. Elements before `vertex` are skipped (list
    properties included), elements after it are not read; list properties of `vertex` itself are
    skipped. Ascii data is read as whitespace-separated words, as rply does (a blank line is no
    row). Colours (`red green blue`) are divided by 255, as Open3D does.

    **Raises:** `PointCloudFileError` (a `ValueError`) naming the file and the line (header,
    ascii data) or byte (binary data): a malformed or unknown header line, a repeated property
    name, no `vertex` element or no `x y z` in it, a word where a number should be, data that
    ends before the element counts.
    """
    with open(path, "rb") as stream:
        data = stream.read()
    fmt, elements, body_start, body_line = _header(data, path)
    if fmt == "ascii":
        return assemble(_read_ascii(data[body_start:], elements, path, body_line), dtype)
    order = "<" if fmt == "binary_little_endian" else ">"
    return assemble(_read_binary(data, body_start, elements, order, path), dtype)


def _header(data, path):
    """(format, elements, offset of the data, line number of the first data line); each element
    is `(name, count, properties)`, a property `(name, kind)` with `kind` a NumPy type code or
    `("list", count code, item code)`."""
    fmt, elements, names_seen, number = None, [], {}, 0
    for number, line, offset in header_lines(data):
        words = line.decode("ascii", "replace").split()
        if number == 1:
            if words != ["ply"]:
                raise line_error(path, 1, "'ply' (not a PLY file)", shown(line.strip()))
            continue
        if not words or words[0] in ("comment", "obj_info"):
            continue
        keyword = words[0]
        if keyword == "end_header":
            body_start = offset
            break
        if keyword == "format":
            if len(words) != 3 or words[1] not in _FORMATS:
                raise line_error(
                    path, number, "'format ascii|binary_little_endian|binary_big_endian 1.0'",
                    shown(line.strip()),
                )  # fmt: skip
            fmt = words[1]
        elif keyword == "element":
            if len(words) != 3 or not words[2].isdigit():
                raise line_error(
                    path, number, "'element <name> <count>' with a count >= 0", shown(line.strip())
                )
            elements.append((words[1], int(words[2]), []))
            names_seen = {}
        elif keyword == "property":
            if not elements:
                raise line_error(path, number, "an 'element' line before it", "a 'property' line")
            name, kind = _property(words, line, path, number)
            if name in names_seen:
                raise line_error(
                    path, number,
                    f"a property name new to element {elements[-1][0]!r}",
                    f"{name!r} again (first on line {names_seen[name]})",
                )  # fmt: skip
            names_seen[name] = number
            elements[-1][2].append((name, kind))
        else:
            raise line_error(
                path, number,
                "a 'format', 'element', 'property', 'comment', 'obj_info' or 'end_header' line",
                shown(line.strip()),
            )  # fmt: skip
    else:
        raise line_error(path, max(number, 1), "'end_header'", "the end of the file")
    if fmt is None:
        raise line_error(path, number, "a 'format' line before 'end_header'", "none")
    vertex = [element for element in elements if element[0] == "vertex"]
    if not vertex:
        raise line_error(path, number, "an 'element vertex' line before 'end_header'", "none")
    scalars = [name for name, kind in vertex[0][2] if not isinstance(kind, tuple)]
    if not {"x", "y", "z"} <= set(scalars):
        raise line_error(
            path, number,
            "properties x, y, z in element 'vertex' before 'end_header'",
            ", ".join(scalars) or "none",
        )  # fmt: skip
    return fmt, elements, body_start, number + 1


def _property(words, line, path, number):
    if len(words) >= 2 and words[1] == "list":
        if len(words) != 5:
            raise line_error(
                path, number, "'property list <count type> <item type> <name>'", shown(line.strip())
            )
        count, item = _type(words[2], path, number), _type(words[3], path, number)
        if count[0] == "f":
            raise line_error(path, number, "an integer list count type", repr(words[2]))
        return words[4], ("list", count, item)
    if len(words) != 3:
        raise line_error(path, number, "'property <type> <name>'", shown(line.strip()))
    return words[2], _type(words[1], path, number)


def _type(name, path, number):
    if name not in _PLY_TYPES:
        raise line_error(path, number, f"a PLY type ({', '.join(_PLY_TYPES)})", f"{shown(name)}")
    return _PLY_TYPES[name]


# ---- ascii --------------------------------------------------------------------------------------


def _read_ascii(body, elements, path, first_line):
    name, count, properties = elements[0]
    if name == "vertex" and not any(isinstance(kind, tuple) for _, kind in properties):
        values = _fast_numbers(body, count * len(properties))  # the common case, in C
        if values is not None:
            values = values.reshape(count, len(properties))
            return {p: values[:, i].astype(kind) for i, (p, kind) in enumerate(properties)}
    words = body.split()
    position = 0
    for name, count, properties in elements:
        if any(isinstance(kind, tuple) for _, kind in properties):
            rows, position = _ascii_lists(
                words, position, name, count, properties, body, path, first_line
            )
        else:
            width = len(properties)
            need = count * width
            if len(words) - position < need:
                raise _ascii_short(
                    body, path, first_line, name, count, width, len(words) - position
                )
            values = _numbers(words, range(position, position + need), body, path, first_line)
            values = values.reshape(count, width)
            rows = {p: values[:, i].astype(kind) for i, (p, kind) in enumerate(properties)}
            position += need
        if name == "vertex":
            return rows
    raise AssertionError("the header has a vertex element")


def _ascii_lists(words, position, name, count, properties, body, path, first_line):
    """Rows of an element with list properties, word by word: its scalars, lists skipped."""
    scalars = {p: [] for p, kind in properties if not isinstance(kind, tuple)}
    for _ in range(count):
        for p, kind in properties:
            if position >= len(words):
                raise line_error(
                    path, last_line(body, first_line),
                    f"{count} rows of element {name!r}", "the end of the file",
                )  # fmt: skip
            if isinstance(kind, tuple):
                length = _numbers(words, [position], body, path, first_line)[0]
                if length != int(length) or length < 0:
                    raise line_error(
                        path, _line_of(body, position, first_line),
                        f"a list length (an integer >= 0) in element {name!r}",
                        shown(words[position]),
                    )  # fmt: skip
                position += 1 + int(length)
            else:
                scalars[p].append(position)
                position += 1
    if position > len(words):
        raise line_error(
            path, last_line(body, first_line), f"{count} rows of element {name!r}",
            "the end of the file",
        )  # fmt: skip
    rows = {p: _numbers(words, scalars[p], body, path, first_line).astype(kind)
            for p, kind in properties if not isinstance(kind, tuple)}  # fmt: skip
    return rows, position


def _fast_numbers(body, count):
    """The first `count` numbers of `body`, or None when it has fewer or a word that is not one
    (the word-by-word reading then names it)."""
    if count == 0:
        return np.zeros(0)
    if not body.strip():  # NumPy 2.4 reads a blank text as [-1]
        return None
    try:  # no `count=`: NumPy 2.4 then pads a short text with uninitialized memory
        values = np.fromstring(body, np.float64, sep=" ")
    except ValueError:
        return None
    return values[:count] if values.size >= count else None


def _numbers(words, indices, body, path, first_line):
    """The words at `indices` (a range or a list) as float64, or an error naming the line of the
    first that is not a number."""
    if isinstance(indices, range):
        chunk = words[indices.start : indices.stop]
    else:
        chunk = [words[k] for k in indices]
    try:
        return np.array(chunk, dtype=bytes).astype(np.float64)
    except ValueError:
        bad = [k for k, word in zip(indices, chunk) if not _is_number(word)][:1]
        if not bad:  # words NumPy does not parse but Python does ("1_000")
            return np.array([float(word) for word in chunk])
        raise line_error(
            path, _line_of(body, bad[0], first_line), "a number", shown(words[bad[0]])
        ) from None


def _is_number(word):
    try:
        float(word)
        return True
    except ValueError:
        return False


def _line_of(body, index, first_line):
    """The line of the `index`-th whitespace-separated word of `body` (slow; for errors only)."""
    for k, match in enumerate(re.finditer(rb"\S+", body)):
        if k == index:
            return first_line + body.count(b"\n", 0, match.start())
    return last_line(body, first_line)


def _ascii_short(body, path, first_line, name, count, width, found):
    return line_error(
        path, last_line(body, first_line),
        f"{count} rows of {width} values for element {name!r} ({count * width} values)",
        f"the file ends after {found}",
    )  # fmt: skip


# ---- binary -------------------------------------------------------------------------------------


def _read_binary(data, offset, elements, order, path):
    for name, count, properties in elements:
        if any(isinstance(kind, tuple) for _, kind in properties):
            rows, offset = _binary_lists(data, offset, name, count, properties, order, path)
        else:
            record = np.dtype([(p, order + kind) for p, kind in properties])
            size = record.itemsize * count
            if len(data) - offset < size:
                raise byte_error(
                    path, offset,
                    f"expected {count} rows of {record.itemsize} bytes for element {name!r} "
                    f"({size} bytes), found the file ends after {len(data) - offset}",
                )  # fmt: skip
            table = np.frombuffer(data, record, count, offset)
            rows = {p: table[p].astype(table[p].dtype.newbyteorder("=")) for p, _ in properties}
            offset += size
        if name == "vertex":
            return rows
    raise AssertionError("the header has a vertex element")


def _binary_lists(data, offset, name, count, properties, order, path):
    """Rows of an element with list properties, row by row: its scalars, lists skipped."""
    scalars = {
        p: np.zeros(count, order + kind) for p, kind in properties if not isinstance(kind, tuple)
    }
    for row in range(count):
        for p, kind in properties:
            code = kind[1] if isinstance(kind, tuple) else kind
            width = np.dtype(code).itemsize
            if offset + width > len(data):
                raise _binary_short(path, offset, name, count, row)
            value = np.frombuffer(data, order + code, 1, offset)[0]
            start, offset = offset, offset + width
            if isinstance(kind, tuple):
                if value < 0:
                    raise byte_error(
                        path, start,
                        f"expected a list length >= 0 in element {name!r}, found {value}",
                    )  # fmt: skip
                offset += int(value) * np.dtype(kind[2]).itemsize
                if offset > len(data):
                    raise _binary_short(path, start, name, count, row)
            else:
                scalars[p][row] = value
    return {
        p: column.astype(column.dtype.newbyteorder("=")) for p, column in scalars.items()
    }, offset


def _binary_short(path, offset, name, count, row):
    return byte_error(
        path, offset,
        f"expected {count} rows of element {name!r}, found the file ends in row {row}",
    )  # fmt: skip


def write_ply(
    path: str | os.PathLike[str],
    points: npt.ArrayLike,
    normals: npt.ArrayLike | None = None,
    colors: npt.ArrayLike | None = None,
    *,
    binary: bool = True,
) -> None:
    """Write points (and optional normals, colors in `[0, 1]`) as a PLY file: float32 x y z, nx ny
    nz, uchar red green blue; binary little endian, or ascii with `binary=False`."""
    points = as_rows(points, "points")
    columns = [("x", "f4"), ("y", "f4"), ("z", "f4")]
    values = [points[:, 0], points[:, 1], points[:, 2]]
    if normals is not None:
        normals = as_rows(normals, "normals", len(points))
        columns += [("nx", "f4"), ("ny", "f4"), ("nz", "f4")]
        values += [normals[:, 0], normals[:, 1], normals[:, 2]]
    if colors is not None:
        colors = np.clip(np.round(as_rows(colors, "colors", len(points)) * 255), 0, 255)
        columns += [("red", "u1"), ("green", "u1"), ("blue", "u1")]
        values += [colors[:, 0], colors[:, 1], colors[:, 2]]
    kinds = {"f4": "float", "u1": "uchar"}
    header = [
        "ply",
        f"format {'binary_little_endian' if binary else 'ascii'} 1.0",
        "comment written by lieax",
        f"element vertex {len(points)}",
        *(f"property {kinds[kind]} {name}" for name, kind in columns),
        "end_header",
    ]
    with open(path, "wb") as stream:
        stream.write(("\n".join(header) + "\n").encode("ascii"))
        if binary:
            record = np.zeros(len(points), np.dtype([(name, "<" + kind) for name, kind in columns]))
            for (name, _), column in zip(columns, values):
                record[name] = column
            stream.write(record.tobytes())
        else:
            formats = ["%.9g" if kind == "f4" else "%d" for _, kind in columns]
            np.savetxt(stream, np.stack(values, axis=1), fmt=formats)
