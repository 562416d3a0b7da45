"""Reading and writing point clouds: PLY (ascii, binary little and big endian), PCD (ascii,
binary, binary_compressed), and NumPy `.npy` / `.npz` arrays.

Everything here runs on the host with NumPy and returns NumPy arrays (wrap them with
`jnp.asarray` to hand them to `lieax.icp`); there is no dependency beyond NumPy.

Formats: PLY after Greg Turk's specification (Stanford, 1994) as Open3D and MeshLab write it; PCD
after the Point Cloud Library's "PCD file format" (v0.7; `binary_compressed` stores each field's
column contiguously, LZF-compressed).
"""

import os
import struct
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


def read_point_cloud(path, *, key=None, dtype=np.float64) -> PointCloudData:
    """Read a `.ply`, `.pcd`, `.npy` or `.npz` file, choosing the format by the extension.

    **Arguments:**
    - `path`: the file.
    - `key`: for `.npz`, the array to read (default `points`, or the only array in the file).
      An `.npy`/`.npz` array of shape `(n, 3)` holds points; `(n, 6)` points then normals.
    - `dtype`: of `points`, `normals` and `colors`.
    """
    extension = os.path.splitext(str(path))[1].lower()
    if extension == ".ply":
        return read_ply(path, dtype=dtype)
    if extension == ".pcd":
        return read_pcd(path, dtype=dtype)
    if extension in (".npy", ".npz"):
        return _read_numpy(path, key, dtype)
    raise ValueError(
        f"Unknown point cloud format {extension!r} for {path}: expected .ply, .pcd, .npy or .npz."
    )


# ---- PLY ----------------------------------------------------------------------------------------

_PLY_TYPES = {
    "char": "i1", "int8": "i1", "uchar": "u1", "uint8": "u1",
    "short": "i2", "int16": "i2", "ushort": "u2", "uint16": "u2",
    "int": "i4", "int32": "i4", "uint": "u4", "uint32": "u4",
    "float": "f4", "float32": "f4", "double": "f8", "float64": "f8",
}  # fmt: skip


def read_ply(path, *, dtype=np.float64) -> PointCloudData:
    """Read the `vertex` element of a PLY file (ascii, binary_little_endian or
    binary_big_endian). Elements before it are skipped; list properties are allowed in elements
    other than `vertex`."""
    with open(path, "rb") as stream:
        header, elements = _ply_header(stream, path)
        fmt = header["format"]
        names = [name for name, _ in elements]
        if "vertex" not in names:
            raise ValueError(f"{path}: the PLY file has no 'vertex' element.")
        fields = None
        for name, element in elements:
            if fmt == "ascii":
                rows = _ply_ascii_element(stream, element, path)
            else:
                rows = _ply_binary_element(stream, element, fmt, path)
            if name == "vertex":
                fields = rows
                break
    return _assemble(fields, path, dtype)


def _ply_header(stream, path):
    first = stream.readline().strip()
    if first != b"ply":
        raise ValueError(f"{path}: not a PLY file (first line {first[:20]!r}).")
    header, elements = {}, []
    while True:
        line = stream.readline()
        if not line:
            raise ValueError(f"{path}: the PLY header has no 'end_header'.")
        words = line.decode("ascii", "replace").split()
        if not words or words[0] in ("comment", "obj_info"):
            continue
        if words[0] == "end_header":
            break
        if words[0] == "format":
            if len(words) < 2 or words[1] not in (
                "ascii",
                "binary_little_endian",
                "binary_big_endian",
            ):
                raise ValueError(f"{path}: unsupported PLY format line {line.strip()!r}.")
            header["format"] = words[1]
        elif words[0] == "element":
            elements.append((words[1], {"count": int(words[2]), "properties": []}))
        elif words[0] == "property":
            if not elements:
                raise ValueError(f"{path}: PLY property before any element.")
            properties = elements[-1][1]["properties"]
            if words[1] == "list":
                properties.append(
                    (words[4], ("list", _ply_type(words[2], path), _ply_type(words[3], path)))
                )
            else:
                properties.append((words[2], _ply_type(words[1], path)))
    if "format" not in header:
        raise ValueError(f"{path}: the PLY header has no 'format' line.")
    return header, elements


def _ply_type(name, path):
    if name not in _PLY_TYPES:
        raise ValueError(f"{path}: unknown PLY property type {name!r}.")
    return _PLY_TYPES[name]


def _ply_ascii_element(stream, element, path):
    count, properties = element["count"], element["properties"]
    lines = [stream.readline() for _ in range(count)]
    if any(isinstance(kind, tuple) for _, kind in properties):
        return None  # a list element (faces): skipped line by line
    if count and not lines[-1]:
        raise ValueError(f"{path}: the PLY file ends before its {count} rows.")
    values = (
        np.loadtxt(lines, dtype=np.float64, ndmin=2) if count else np.zeros((0, len(properties)))
    )
    if values.shape[1] < len(properties):
        raise ValueError(
            f"{path}: PLY rows have {values.shape[1]} values, expected {len(properties)}."
        )
    return {name: values[:, i].astype(kind) for i, (name, kind) in enumerate(properties)}


def _ply_binary_element(stream, element, fmt, path):
    count, properties = element["count"], element["properties"]
    order = "<" if fmt == "binary_little_endian" else ">"
    if any(isinstance(kind, tuple) for _, kind in properties):
        for _ in range(count):  # skip a list element row by row
            for _, kind in properties:
                if isinstance(kind, tuple):
                    size_type, item_type = np.dtype(order + kind[1]), np.dtype(order + kind[2])
                    length = int(np.frombuffer(stream.read(size_type.itemsize), size_type)[0])
                    stream.read(length * item_type.itemsize)
                else:
                    stream.read(np.dtype(kind).itemsize)
        return None
    record = np.dtype([(name, order + kind) for name, kind in properties])
    data = stream.read(record.itemsize * count)
    if len(data) < record.itemsize * count:
        raise ValueError(f"{path}: the PLY file ends before its {count} rows.")
    rows = np.frombuffer(data, record, count)
    return {name: rows[name].astype(rows[name].dtype.newbyteorder("=")) for name, _ in properties}


def write_ply(path, points, normals=None, colors=None, *, binary=True):
    """Write points (and optional normals, colors in `[0, 1]`) as a PLY file: float32 x y z, nx ny
    nz, uchar red green blue; binary little endian, or ascii with `binary=False`."""
    points = _as_rows(points, "points")
    columns = [("x", "f4"), ("y", "f4"), ("z", "f4")]
    values = [points[:, 0], points[:, 1], points[:, 2]]
    if normals is not None:
        normals = _as_rows(normals, "normals", len(points))
        columns += [("nx", "f4"), ("ny", "f4"), ("nz", "f4")]
        values += [normals[:, 0], normals[:, 1], normals[:, 2]]
    if colors is not None:
        colors = np.clip(np.round(_as_rows(colors, "colors", len(points)) * 255), 0, 255)
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


# ---- PCD ----------------------------------------------------------------------------------------

_PCD_TYPES = {("F", 4): "f4", ("F", 8): "f8", ("I", 1): "i1", ("I", 2): "i2", ("I", 4): "i4",
              ("I", 8): "i8", ("U", 1): "u1", ("U", 2): "u2", ("U", 4): "u4", ("U", 8): "u8"}  # fmt: skip


def read_pcd(path, *, dtype=np.float64) -> PointCloudData:
    """Read a PCD file (v0.5 to v0.7; DATA ascii, binary or binary_compressed). Organized clouds
    (HEIGHT > 1) are flattened row by row; their invalid points stay NaN."""
    with open(path, "rb") as stream:
        header = {}
        while True:
            line = stream.readline()
            if not line:
                raise ValueError(f"{path}: the PCD header has no DATA line.")
            words = line.decode("ascii", "replace").split()
            if not words or words[0].startswith("#"):
                continue
            header[words[0].upper()] = words[1:]
            if words[0].upper() == "DATA":
                break
        body = stream.read()
    for required in ("FIELDS", "SIZE", "TYPE"):
        if required not in header:
            raise ValueError(f"{path}: the PCD header has no {required} line.")
    names = header["FIELDS"]
    sizes = [int(s) for s in header["SIZE"]]
    types = [t.upper() for t in header["TYPE"]]
    counts = [int(c) for c in header.get("COUNT", ["1"] * len(names))]
    if not len(names) == len(sizes) == len(types) == len(counts):
        raise ValueError(f"{path}: PCD FIELDS, SIZE, TYPE and COUNT lengths differ.")
    if "POINTS" in header:
        n = int(header["POINTS"][0])
    else:
        n = int(header["WIDTH"][0]) * int(header.get("HEIGHT", ["1"])[0])
    kinds = []
    for name, size, kind in zip(names, sizes, types):
        if (kind, size) not in _PCD_TYPES:
            raise ValueError(f"{path}: unsupported PCD field {name!r} of type {kind}{size}.")
        kinds.append(_PCD_TYPES[(kind, size)])
    mode = header["DATA"][0].lower()
    record = np.dtype(
        [(f"f{i}", "<" + kind, (count,)) for i, (kind, count) in enumerate(zip(kinds, counts))]
    )
    if mode == "ascii":
        text = body.decode("ascii", "replace").split("\n")
        text = [row for row in text if row.strip()][:n]
        flat = np.loadtxt(text, dtype=np.float64, ndmin=2) if n else np.zeros((0, sum(counts)))
        columns, start = {}, 0
        for i, count in enumerate(counts):
            columns[i] = flat[:, start : start + count]
            start += count
        raw = {i: columns[i].astype(kinds[i]) for i in range(len(names))}
        if "rgb" in names or "rgba" in names:  # packed colours are written as float bit patterns
            for i, name in enumerate(names):
                if name in ("rgb", "rgba") and kinds[i] == "f4":
                    raw[i] = flat[:, sum(counts[:i])].astype(np.float32)[:, None]
    elif mode == "binary":
        if len(body) < record.itemsize * n:
            raise ValueError(f"{path}: the PCD file ends before its {n} points.")
        rows = np.frombuffer(body[: record.itemsize * n], record, n)
        raw = {i: rows[f"f{i}"] for i in range(len(names))}
    elif mode == "binary_compressed":
        compressed, uncompressed = struct.unpack("<II", body[:8])
        data = _lzf_decompress(body[8 : 8 + compressed], uncompressed)
        raw, offset = {}, 0
        for i, (kind, count) in enumerate(zip(kinds, counts)):
            width = np.dtype(kind).itemsize * count
            raw[i] = np.frombuffer(data[offset : offset + width * n], "<" + kind).reshape(n, count)
            offset += width * n
    else:
        raise ValueError(f"{path}: unsupported PCD DATA mode {mode!r}.")
    fields = {}
    for i, name in enumerate(names):
        if name == "_":
            continue
        column = np.asarray(raw[i]).reshape(n, counts[i])
        fields[name] = column[:, 0] if counts[i] == 1 else column
    return _assemble(fields, path, dtype)


def _lzf_decompress(data, size):
    """LZF decompression (Marc Lehmann's liblzf format, as PCL's binary_compressed uses)."""
    out = bytearray(size)
    i = j = 0
    n = len(data)
    while i < n:
        control = data[i]
        i += 1
        if control < 32:  # a literal run of control + 1 bytes
            length = control + 1
            out[j : j + length] = data[i : i + length]
            i += length
            j += length
        else:  # a back reference
            length = control >> 5
            if length == 7:
                length += data[i]
                i += 1
            reference = j - ((control & 0x1F) << 8) - data[i] - 1
            i += 1
            for _ in range(length + 2):  # may overlap its own output
                out[j] = out[reference]
                j += 1
                reference += 1
    if j != size:
        raise ValueError(f"LZF data decompressed to {j} bytes, expected {size}.")
    return bytes(out)


def write_pcd(path, points, normals=None, *, binary=True):
    """Write points (and optional normals) as a PCD v0.7 file of float32 fields, DATA binary (or
    ascii with `binary=False`)."""
    points = _as_rows(points, "points")
    names, values = ["x", "y", "z"], [points]
    if normals is not None:
        names += ["normal_x", "normal_y", "normal_z"]
        values.append(_as_rows(normals, "normals", len(points)))
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


# ---- NumPy --------------------------------------------------------------------------------------


def _read_numpy(path, key, dtype):
    if str(path).lower().endswith(".npy"):
        array = np.load(path, allow_pickle=False)
        where = str(path)
    else:
        with np.load(path, allow_pickle=False) as archive:
            names = list(archive.keys())
            if key is None:
                if "points" in names:
                    key = "points"
                elif len(names) == 1:
                    key = names[0]
                else:
                    raise ValueError(
                        f"{path} holds several arrays ({', '.join(names)}); pass key= to choose one."
                    )
            if key not in names:
                raise KeyError(f"{path} has no array {key!r} (it has {', '.join(names)}).")
            array = archive[key]
        where = f"{path}[{key!r}]"
    array = np.asarray(array)
    if array.ndim != 2 or array.shape[1] not in (3, 6):
        raise ValueError(
            f"{where} must have shape (n, 3) (points) or (n, 6) (points, normals), got {array.shape}."
        )
    normals = array[:, 3:6].astype(dtype) if array.shape[1] == 6 else None
    fields = {
        name: array[:, i]
        for i, name in enumerate(("x", "y", "z", "nx", "ny", "nz")[: array.shape[1]])
    }
    return PointCloudData(array[:, :3].astype(dtype), normals, None, fields)


# ---- shared -------------------------------------------------------------------------------------


def _assemble(fields, path, dtype):
    def pick(*options):
        for names in options:
            if all(name in fields for name in names):
                return np.stack([np.asarray(fields[name], np.float64) for name in names], axis=1)
        return None

    points = pick(("x", "y", "z"))
    if points is None:
        raise ValueError(f"{path}: the file has no x, y, z fields (it has {', '.join(fields)}).")
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


def _as_rows(array, what, count=None):
    array = np.asarray(array, np.float64)
    if array.ndim != 2 or array.shape[1] != 3:
        raise ValueError(f"{what} must have shape (n, 3), got {array.shape}.")
    if count is not None and len(array) != count:
        raise ValueError(f"{what} must have {count} rows (one per point), got {len(array)}.")
    return array
