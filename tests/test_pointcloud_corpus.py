"""A corpus of unusual and malformed PLY/PCD files, written from a table of cases.

Each file is either read (points, colours and fields checked against the values the case was
built from, and against Open3D's reader when Open3D imports) or refused with a
`PointCloudFileError` whose message names the file and the line or byte.
"""

import os
import re

import numpy as np
import pytest

import lieax.io as pcio

DATA_DIR = os.environ.get("LIEAX_DATA_DIR")
N = 40
_rng = np.random.default_rng(7)
POINTS = np.round(_rng.normal(size=(N, 3)) * 8) / 8  # exact in float32 and in ascii
COLORS = _rng.integers(0, 256, size=(N, 3))
PACKED = (COLORS[:, 0] << 16 | COLORS[:, 1] << 8 | COLORS[:, 2]).astype(np.uint32)


def _ascii_rows(*columns, fmt="%.6g"):
    table = np.column_stack(columns)
    return "".join(" ".join(fmt % v for v in row) + "\n" for row in table)


def _ply_header(fmt, properties, count=N, before="", after=""):
    return (
        f"ply\nformat {fmt} 1.0\n{before}element vertex {count}\n"
        + "".join(f"property {p}\n" for p in properties)
        + after
        + "end_header\n"
    )


XYZ = ["float x", "float y", "float z"]
PLY_ASCII = _ply_header("ascii", XYZ) + _ascii_rows(POINTS)


def _binary(columns, order="<"):
    """Rows of binary data from `(NumPy type, column)` pairs."""
    record = np.dtype([(f"c{i}", order + kind) for i, (kind, _) in enumerate(columns)])
    table = np.zeros(N, record)
    for i, (_, column) in enumerate(columns):
        table[f"c{i}"] = column
    return table.tobytes()


PLY_BINARY = _ply_header("binary_little_endian", XYZ).encode() + _binary(
    [("f4", POINTS[:, 0]), ("f4", POINTS[:, 1]), ("f4", POINTS[:, 2])]
)


def _pcd_header(fields, sizes, types, counts=None, *, width=N, height=1, points=N, data="ascii"):
    lines = [
        "# .PCD v0.7 - Point Cloud Data file format",
        "VERSION 0.7",
        "FIELDS " + " ".join(fields),
        "SIZE " + " ".join(map(str, sizes)),
        "TYPE " + " ".join(types),
        "COUNT " + " ".join(map(str, counts or [1] * len(fields))),
        f"WIDTH {width}" if width is not None else None,
        f"HEIGHT {height}" if height is not None else None,
        "VIEWPOINT 0 0 0 1 0 0 0",
        f"POINTS {points}" if points is not None else None,
        f"DATA {data}",
    ]
    return "".join(line + "\n" for line in lines if line is not None)


PCD_XYZ = dict(fields=["x", "y", "z"], sizes=[4, 4, 4], types=["F", "F", "F"])
PCD_ASCII = _pcd_header(**PCD_XYZ) + _ascii_rows(POINTS)


def _lzf_literals(data):
    """Valid LZF of `data` made only of literal runs (at most 32 bytes each)."""
    out = bytearray()
    for start in range(0, len(data), 32):
        chunk = data[start : start + 32]
        out += bytes([len(chunk) - 1]) + chunk
    return bytes(out)


def _compressed(columns, *, stream=None, uncompressed=None):
    """A binary_compressed PCD body: each column contiguous, LZF (literal runs unless `stream`)."""
    table = b"".join(np.asarray(column, "<" + kind).tobytes() for kind, column in columns)
    stream = _lzf_literals(table) if stream is None else stream
    sizes = np.array([len(stream), uncompressed or len(table)], "<u4")
    return sizes.tobytes() + stream


PCD_COMPRESSED_HEAD = _pcd_header(**PCD_XYZ, data="binary_compressed").encode()
XYZ_COLUMNS = [("f4", POINTS[:, 0]), ("f4", POINTS[:, 1]), ("f4", POINTS[:, 2])]


def _overlap_case():
    """8 points, x from an overlapping back reference, y and z literal zeros."""
    x = np.tile(np.array([1.5, -2.25], np.float32), 4)
    # literal 8 bytes, then a back reference of 24 bytes from 8 back (L = 7 + 15, distance 8)
    stream = bytes([7]) + x[:2].tobytes() + bytes([0xE0, 24 - 2 - 7, 8 - 1])
    stream += _lzf_literals(bytes(64))
    head = _pcd_header(**PCD_XYZ, width=8, points=8, data="binary_compressed").encode()
    body = np.array([len(stream), 96], "<u4").tobytes() + stream
    return head + body, np.column_stack([x, np.zeros(8), np.zeros(8)])


# ---- files that are read --------------------------------------------------------------------

READ = {
    # PLY
    "ply_ascii_blank_line_before_rows.ply": (
        PLY_ASCII.replace("end_header\n", "end_header\n\n"),
        dict(),
    ),
    "ply_ascii_blank_lines_between_rows.ply": (
        PLY_ASCII.replace("\n", "\n\n").replace("\n\n", "\n", 8),
        dict(),
    ),
    "ply_ascii_crlf.ply": (PLY_ASCII.replace("\n", "\r\n"), dict()),
    "ply_binary_crlf_header.ply": (
        _ply_header("binary_little_endian", XYZ).replace("\n", "\r\n").encode()
        + PLY_BINARY[-12 * N :],
        dict(),
    ),
    "ply_comments_obj_info.ply": (
        PLY_ASCII.replace(
            "format ascii 1.0\n", "format ascii 1.0\ncomment made by hand\nobj_info scanner 3\n"
        ),
        dict(),
    ),
    "ply_bare_comment.ply": (
        PLY_ASCII.replace("format ascii 1.0\n", "format ascii 1.0\ncomment\n"),
        dict(open3d=False),  # rply refuses a comment without text; the spec allows it
    ),
    "ply_vertex_list_property_ascii.ply": (
        _ply_header("ascii", ["float x", "list uchar float texcoord", "float y", "float z"])
        + "".join(
            f"{x:g} {k % 3} " + " 0.5" * (k % 3) + f" {y:g} {z:g}\n"
            for k, (x, y, z) in enumerate(POINTS)
        ),
        dict(),
    ),
    "ply_vertex_list_property_binary.ply": (
        _ply_header("binary_little_endian", XYZ + ["list uchar int ids"]).encode()
        + b"".join(
            np.array(p, "<f4").tobytes() + bytes([k % 4]) + np.arange(k % 4, dtype="<i4").tobytes()
            for k, p in enumerate(POINTS)
        ),
        dict(),
    ),
    "ply_faces_before_and_after_ascii.ply": (
        _ply_header(
            "ascii",
            XYZ,
            before="element face 2\nproperty list uchar int vertex_indices\nproperty uchar flag\n",
            after="element edge 1\nproperty int vertex1\nproperty int vertex2\n",
        ).replace("element vertex", "element camera 1\nproperty float k\nelement vertex")
        + "3 0 1 2 7\n4 0 1 2 3 9\n"
        + "0.5\n"
        + _ascii_rows(POINTS)
        + "0 1\n",
        dict(),
    ),
    "ply_faces_before_binary_big_endian.ply": (
        _ply_header(
            "binary_big_endian",
            ["double x", "double y", "double z"],
            before="element face 2\nproperty list uchar int vertex_indices\n",
        ).encode()
        + b"\x03"
        + np.arange(3, dtype=">i4").tobytes()
        + b"\x00"
        + _binary([("f8", POINTS[:, 0]), ("f8", POINTS[:, 1]), ("f8", POINTS[:, 2])], ">"),
        dict(),
    ),
    "ply_type_aliases_and_colours.ply": (
        _ply_header(
            "binary_little_endian",
            [
                "float64 x",
                "float32 y",
                "double z",
                "uint8 red",
                "uchar green",
                "uint8 blue",
                "int8 tag",
                "char tag2",
                "int16 a",
                "uint16 b",
                "int32 c",
                "uint32 d",
            ],
        ).encode()
        + _binary(
            [("f8", POINTS[:, 0]), ("f4", POINTS[:, 1]), ("f8", POINTS[:, 2])]
            + [("u1", COLORS[:, i]) for i in range(3)]
            + [("i1", -np.arange(N)), ("i1", np.arange(N)), ("i2", -np.arange(N) * 300)]
            + [("u2", np.arange(N) * 1000), ("i4", -np.arange(N) * 10**6)]
            + [("u4", np.arange(N) * 10**8)]
        ),
        dict(colors=COLORS / 255, fields={"tag": -np.arange(N), "d": np.arange(N) * 10**8}),
    ),
    "ply_ascii_integer_types.ply": (
        _ply_header("ascii", XYZ + ["uchar red", "uchar green", "uchar blue", "int8 t"])
        + _ascii_rows(POINTS, COLORS, -np.arange(N)),
        dict(colors=COLORS / 255, fields={"t": -np.arange(N)}),
    ),
    "ply_empty_vertex_element.ply": (_ply_header("ascii", XYZ, count=0), dict(count=0)),
    # PCD
    "pcd_rgb_uint32_decimal_type_u.pcd": (
        _pcd_header(["x", "y", "z", "rgb"], [4] * 4, ["F", "F", "F", "U"])
        + _ascii_rows(POINTS, PACKED, fmt="%.10g"),
        dict(colors=COLORS / 255),
    ),
    "pcd_rgb_uint32_decimal_type_f.pcd": (  # PCL >= 1.8 writes TYPE F rgb as a uint32 in ascii
        _pcd_header(["x", "y", "z", "rgb"], [4] * 4, ["F", "F", "F", "F"])
        + _ascii_rows(POINTS, PACKED, fmt="%.10g"),
        dict(colors=COLORS / 255, open3d=False),  # Open3D parses the integer as a float
    ),
    "pcd_rgb_float_packed_ascii.pcd": (  # PCL < 1.8: the float whose bits are the colour
        _pcd_header(["x", "y", "z", "rgb"], [4] * 4, ["F", "F", "F", "F"])
        + "".join(
            f"{x:g} {y:g} {z:g} {c:.9g}\n" for (x, y, z), c in zip(POINTS, PACKED.view(np.float32))
        ),
        dict(colors=COLORS / 255),
    ),
    "pcd_rgb_float_packed_binary.pcd": (
        _pcd_header(["x", "y", "z", "rgb"], [4] * 4, ["F"] * 4, data="binary").encode()
        + _binary(XYZ_COLUMNS + [("u4", PACKED)]),
        dict(colors=COLORS / 255),
    ),
    "pcd_rgba_uint32_binary.pcd": (
        _pcd_header(["x", "y", "z", "rgba"], [4] * 4, ["F", "F", "F", "U"], data="binary").encode()
        + _binary(XYZ_COLUMNS + [("u4", PACKED | 0x80000000)]),
        dict(colors=COLORS / 255),
    ),
    "pcd_count_3_and_padding_ascii.pcd": (
        _pcd_header(
            ["x", "y", "z", "hist", "_"],
            [4, 4, 4, 2, 1],
            ["F", "F", "F", "U", "U"],
            [1, 1, 1, 3, 2],
        )
        + _ascii_rows(POINTS, np.arange(3 * N).reshape(N, 3), np.zeros((N, 2))),
        dict(fields={"hist": np.arange(3 * N).reshape(N, 3)}),
    ),
    "pcd_count_3_and_padding_binary.pcd": (
        _pcd_header(
            ["x", "_", "y", "z", "hist"],
            [4, 1, 4, 4, 8],
            ["F", "U", "F", "F", "F"],
            [1, 3, 1, 1, 2],
            data="binary",
        ).encode()
        + _binary(
            [("f4", POINTS[:, 0]), ("u1", 0), ("u1", 0), ("u1", 0)]
            + XYZ_COLUMNS[1:]
            + [("f8", np.arange(N)), ("f8", -np.arange(N))]
        ),
        dict(fields={"hist": np.column_stack([np.arange(N), -np.arange(N)])}),
    ),
    "pcd_count_2_compressed.pcd": (
        _pcd_header(
            ["x", "y", "z", "uv"],
            [4, 4, 4, 2],
            ["F", "F", "F", "I"],
            [1, 1, 1, 2],
            data="binary_compressed",
        ).encode()
        + _compressed(XYZ_COLUMNS + [("i2", -np.arange(2 * N))]),
        dict(fields={"uv": -np.arange(2 * N).reshape(N, 2)}),
    ),
    "pcd_compressed_literals.pcd": (PCD_COMPRESSED_HEAD + _compressed(XYZ_COLUMNS), dict()),
    "pcd_viewpoint_not_applied.pcd": (
        PCD_ASCII.replace("VIEWPOINT 0 0 0 1 0 0 0", "VIEWPOINT 1 2 3 0 0 0 1"),
        dict(),
    ),
    "pcd_ascii_nan_rows.pcd": (
        PCD_ASCII.replace(_ascii_rows(POINTS[3:4]), "nan nan nan\n", 1),
        dict(points=np.where(np.arange(N)[:, None] == 3, np.nan, POINTS)),
    ),
    "pcd_organized_width_height.pcd": (
        _pcd_header(**PCD_XYZ, width=8, height=5, points=None) + _ascii_rows(POINTS),
        dict(),
    ),
    "pcd_width_height_differ_from_points.pcd": (
        _pcd_header(**PCD_XYZ, width=7, height=3) + _ascii_rows(POINTS),
        dict(),  # POINTS wins, as in Open3D
    ),
    "pcd_no_width_height.pcd": (
        _pcd_header(**PCD_XYZ, width=None, height=None) + _ascii_rows(POINTS),
        dict(),
    ),
    "pcd_crlf_ascii.pcd": (PCD_ASCII.replace("\n", "\r\n"), dict()),
    "pcd_blank_lines_in_ascii.pcd": (PCD_ASCII.replace("\n", "\n\n"), dict()),
    "pcd_lowercase_types_and_extra_rows.pcd": (
        PCD_ASCII.replace("TYPE F F F", "TYPE f f f") + "1 2 3\n",
        dict(),
    ),
}

# ---- files that are refused: (content, pattern after the file name) ------------------------

_PCD_CORRUPT = bytearray(PCD_COMPRESSED_HEAD + _compressed(XYZ_COLUMNS))
_PCD_CORRUPT[len(PCD_COMPRESSED_HEAD) + 8] = 0x20  # a back reference before any output
PLY_HEAD = len(PLY_BINARY) - 12 * N  # header bytes
PCD_HEAD = len(_pcd_header(**PCD_XYZ, data="binary"))  # binary_compressed: 11 bytes more
_PLY_ROWS = PLY_ASCII.split("end_header\n")[1].splitlines(keepends=True)

REFUSED = {
    # PLY header
    "ply_not_ply.ply": ("plyx\nformat ascii 1.0\n", r":1: expected 'ply' \(not a PLY file\)"),
    "ply_no_end_header.ply": (
        _ply_header("ascii", XYZ).replace("end_header\n", ""),
        r":6: expected 'end_header', found the end of the file",
    ),
    "ply_no_format.ply": (
        PLY_ASCII.replace("format ascii 1.0\n", ""),
        r":6: expected a 'format' line before 'end_header'",
    ),
    "ply_bad_format.ply": (
        PLY_ASCII.replace("format ascii 1.0", "format binary 1.0"),
        r":2: expected 'format ascii\|binary_little_endian\|binary_big_endian 1.0'",
    ),
    "ply_word_for_element_count.ply": (
        PLY_ASCII.replace(f"vertex {N}", "vertex forty"),
        r":3: expected 'element <name> <count>' with a count >= 0, found 'element vertex forty'",
    ),
    "ply_unknown_type.ply": (
        PLY_ASCII.replace("float y", "real y"),
        r":5: expected a PLY type \(.*\), found 'real'",
    ),
    "ply_repeated_property.ply": (
        PLY_ASCII.replace("float z", "float x"),
        r":6: expected a property name new to element 'vertex', found 'x' again "
        r"\(first on line 4\)",
    ),
    "ply_property_before_element.ply": (
        "ply\nformat ascii 1.0\nproperty float x\nend_header\n",
        r":3: expected an 'element' line before it",
    ),
    "ply_unknown_keyword.ply": (
        PLY_ASCII.replace("end_header", "vertex_count 3\nend_header"),
        r":7: expected a 'format', 'element', .* line, found 'vertex_count 3'",
    ),
    "ply_no_vertex.ply": (
        "ply\nformat ascii 1.0\nelement face 0\nproperty list uchar int v\nend_header\n",
        r":5: expected an 'element vertex' line",
    ),
    "ply_no_z.ply": (
        _ply_header("ascii", ["float x", "float y", "list uchar float z"]),
        r":7: expected properties x, y, z in element 'vertex' .*, found x, y",
    ),
    "ply_float_list_count.ply": (
        _ply_header("ascii", XYZ + ["list float int v"]),
        r":7: expected an integer list count type, found 'float'",
    ),
    # PLY ascii data
    "ply_ascii_word_for_value.ply": (
        PLY_ASCII.replace(_PLY_ROWS[4], "1 2 abc\n"),
        r":12: expected a number, found 'abc'",
    ),
    "ply_ascii_truncated_rows.ply": (
        PLY_ASCII[: PLY_ASCII.index(_PLY_ROWS[-1])],
        rf":46: expected {N} rows of 3 values for element 'vertex' \({3 * N} values\), found the "
        rf"file ends after {3 * N - 3}",
    ),
    "ply_ascii_count_larger_than_data.ply": (
        PLY_ASCII.replace(f"vertex {N}", f"vertex {N + 5}"),
        rf":47: expected {N + 5} rows of 3 values",
    ),
    "ply_ascii_list_length_word.ply": (
        _ply_header("ascii", XYZ + ["list uchar int v"]) + "0 0 0 x 1\n",
        r":9: expected a number, found 'x'",
    ),
    "ply_ascii_list_truncated.ply": (
        _ply_header("ascii", XYZ + ["list uchar int v"], count=2) + "0 0 0 3 1 2 3\n0 0 0 4 1\n",
        r":10: expected 2 rows of element 'vertex', found the end of the file",
    ),
    # PLY binary data
    "ply_binary_truncated.ply": (
        PLY_BINARY[:-5],
        rf": byte {PLY_HEAD}: expected {N} rows of 12 bytes for element 'vertex' "
        rf"\({12 * N} bytes\), "
        rf"found the file ends after {12 * N - 5}",
    ),
    "ply_binary_list_truncated.ply": (
        _ply_header("binary_little_endian", XYZ + ["list uchar int v"], count=2).encode()
        + bytes(12)
        + b"\x02"
        + bytes(8)
        + bytes(12)
        + b"\x05"
        + bytes(8),
        # the header has 25 bytes more than PLY_HEAD; row 0 has 21 bytes, row 1 its list at 12
        rf": byte {PLY_HEAD + 25 + 21 + 12}: expected 2 rows of element 'vertex', found the file "
        "ends in row 1",
    ),
    # PCD header
    "pcd_no_data_line.pcd": (PCD_ASCII.split("DATA")[0], r":10: expected a 'DATA' line ending"),
    "pcd_bad_data_mode.pcd": (
        PCD_ASCII.replace("DATA ascii", "DATA binary_lz4"),
        r":11: expected 'DATA ascii\|binary\|binary_compressed', found 'DATA binary_lz4'",
    ),
    "pcd_no_fields.pcd": (
        PCD_ASCII.replace("FIELDS x y z\n", ""),
        r":10: expected a FIELDS line before DATA",
    ),
    "pcd_word_for_size.pcd": (
        PCD_ASCII.replace("SIZE 4 4 4", "SIZE 4 four 4"),
        r":4: expected an integer in SIZE, found 'four'",
    ),
    "pcd_word_for_points.pcd": (
        PCD_ASCII.replace(f"POINTS {N}", "POINTS many"),
        r":10: expected an integer in POINTS, found 'many'",
    ),
    "pcd_two_widths.pcd": (
        PCD_ASCII.replace(f"WIDTH {N}", f"WIDTH {N} 1"),
        rf":7: expected one integer >= 0 after WIDTH, found {N} 1",
    ),
    "pcd_no_points_no_width.pcd": (
        _pcd_header(**PCD_XYZ, width=None, points=None) + _ascii_rows(POINTS),
        r":9: expected a POINTS or WIDTH line before DATA, found neither",
    ),
    "pcd_size_type_lengths_differ.pcd": (
        PCD_ASCII.replace("TYPE F F F", "TYPE F F"),
        r":5: expected 3 TYPE entries \(one per field of FIELDS\), found 2",
    ),
    "pcd_unsupported_type.pcd": (
        PCD_ASCII.replace("SIZE 4 4 4", "SIZE 4 2 4"),
        r":5: expected a TYPE F \(SIZE 4, 8\), I or U .* for field 'y', found TYPE F SIZE 2",
    ),
    "pcd_count_2_for_x.pcd": (
        PCD_ASCII.replace("COUNT 1 1 1", "COUNT 2 1 1"),
        r":6: expected COUNT 1 for field 'x', found 2",
    ),
    "pcd_repeated_field.pcd": (
        PCD_ASCII.replace("FIELDS x y z", "FIELDS x y x"),
        r":3: expected field names used once, found 'x' twice",
    ),
    "pcd_no_z.pcd": (
        PCD_ASCII.replace("FIELDS x y z", "FIELDS x y w"),
        r":3: expected fields x, y, z, found x, y, w",
    ),
    "pcd_bad_viewpoint.pcd": (
        PCD_ASCII.replace("VIEWPOINT 0 0 0 1 0 0 0", "VIEWPOINT 0 0 0 1"),
        r":9: expected 7 VIEWPOINT numbers \(tx ty tz qw qx qy qz\), found 4",
    ),
    # PCD ascii data
    "pcd_ascii_word_for_value.pcd": (
        PCD_ASCII.replace(_PLY_ROWS[2], "1 two 3\n"),
        r":14: expected a number \(value 2 of the row\), found 'two'",
    ),
    "pcd_ascii_short_row.pcd": (
        PCD_ASCII.replace(_PLY_ROWS[5], "1 2\n"),
        r":17: expected 3 values in a point row, found 2: '1 2'",
    ),
    "pcd_ascii_truncated.pcd": (
        PCD_ASCII[: PCD_ASCII.index(_PLY_ROWS[-3])],
        rf":48: expected {N} point rows, found the file ends after {N - 3}",
    ),
    # PCD binary data
    "pcd_binary_truncated.pcd": (
        _pcd_header(**PCD_XYZ, data="binary").encode() + PLY_BINARY[-12 * N : -1],
        rf": byte {PCD_HEAD}: expected {N} points of 12 bytes \({12 * N} bytes\), "
        r"found the file ends "
        rf"after {12 * N - 1}",
    ),
    "pcd_compressed_back_reference_before_start.pcd": (
        bytes(_PCD_CORRUPT),
        rf": byte {PCD_HEAD + 19}: LZF back reference \d+ bytes back from output byte 0, "
        "before the start",
    ),
    "pcd_compressed_only_back_references.pcd": (  # read as 40 points at 0 before the fix
        PCD_COMPRESSED_HEAD + _compressed(XYZ_COLUMNS, stream=bytes([0xE0, 253, 0, 0xE0, 209, 0])),
        rf": byte {PCD_HEAD + 19}: LZF back reference 1 bytes back from output byte 0, before",
    ),
    "pcd_compressed_truncated_stream.pcd": (
        PCD_COMPRESSED_HEAD + _compressed(XYZ_COLUMNS)[:-40],
        rf": byte {PCD_HEAD + 11}: expected {12 * N + 15} bytes of compressed data, "
        r"found the file ends after \d+",
    ),
    "pcd_compressed_literal_past_end.pcd": (
        PCD_COMPRESSED_HEAD + _compressed(XYZ_COLUMNS, stream=b"\x1f" + bytes(10)),
        rf": byte {PCD_HEAD + 19}: LZF literal run of 32 bytes goes past the end of the "
        "compressed data",
    ),
    "pcd_compressed_stream_short.pcd": (
        PCD_COMPRESSED_HEAD + _compressed(XYZ_COLUMNS, stream=_lzf_literals(bytes(64))),
        rf": byte {PCD_HEAD + 19 + 66}: LZF data ends after 64 uncompressed bytes, "
        rf"expected {12 * N}",
    ),
    "pcd_compressed_writes_past_size.pcd": (
        PCD_COMPRESSED_HEAD + _compressed(XYZ_COLUMNS, stream=_lzf_literals(bytes(12 * N + 1))),
        rf": byte {PCD_HEAD + 19 + 33 * 15}: LZF chunk writes up to byte {12 * N + 1}, "
        "past the declared",
    ),
    "pcd_compressed_wrong_uncompressed_size.pcd": (
        PCD_COMPRESSED_HEAD + _compressed(XYZ_COLUMNS, uncompressed=12 * N - 4),
        rf": byte {PCD_HEAD + 15}: expected an uncompressed size of {12 * N} bytes "
        rf"\({N} points of 12\), "
        rf"found {12 * N - 4}",
    ),
    "pcd_compressed_no_sizes.pcd": (
        PCD_COMPRESSED_HEAD + b"\x01\x02",
        rf": byte {PCD_HEAD + 11}: expected the 8-byte sizes of binary_compressed data, "
        "found 2 bytes",
    ),
}


def _write(tmp_path, name, content):
    path = tmp_path / name
    path.write_bytes(content if isinstance(content, bytes) else content.encode())
    return path


@pytest.mark.parametrize("name", sorted(READ))
def test_read(tmp_path, name):
    content, expected = READ[name]
    path = _write(tmp_path, name, content)
    cloud = pcio.read_point_cloud(path)
    count = expected.get("count", N)
    points = expected.get("points", POINTS)[:count]
    np.testing.assert_array_equal(cloud.points, points)
    if "colors" in expected:
        np.testing.assert_allclose(cloud.colors, expected["colors"], atol=1e-12)
    for field, values in expected.get("fields", {}).items():
        np.testing.assert_array_equal(cloud.fields[field], values)
    assert "_" not in cloud.fields
    if not expected.get("open3d", True):
        return
    o3d = pytest.importorskip("open3d")
    reference = o3d.io.read_point_cloud(str(path))  # keeps NaN points by default
    np.testing.assert_array_equal(np.asarray(reference.points), cloud.points)
    if reference.has_colors():
        np.testing.assert_allclose(np.asarray(reference.colors), cloud.colors, atol=1e-12)


@pytest.mark.parametrize("name", sorted(REFUSED))
def test_refused(tmp_path, name):
    content, pattern = REFUSED[name]
    path = _write(tmp_path, name, content)
    with pytest.raises(pcio.PointCloudFileError, match=re.escape(str(path)) + pattern):
        pcio.read_point_cloud(path)


def test_overlapping_back_reference(tmp_path):
    """An LZF copy longer than its distance repeats the last `distance` bytes (liblzf)."""
    content, points = _overlap_case()
    path = _write(tmp_path, "overlap.pcd", content)
    np.testing.assert_array_equal(pcio.read_pcd(path).points, points)
    o3d = pytest.importorskip("open3d")
    np.testing.assert_array_equal(np.asarray(o3d.io.read_point_cloud(str(path)).points), points)


@pytest.mark.skipif(DATA_DIR is None, reason="set LIEAX_DATA_DIR to the shared data")
def test_office_kinect_binary_compressed():
    """The largest shared cloud: PCL's office1.pcd, 640 x 480 organized, x y z rgb."""
    path = os.path.join(DATA_DIR, "clouds", "office_kinect", "office1.pcd")
    cloud = pcio.read_point_cloud(path)
    assert cloud.points.shape == (640 * 480, 3) and cloud.colors.shape == (640 * 480, 3)
    assert np.isfinite(cloud.points).all(axis=1).sum() == 254_456  # the data README's count
    assert cloud.colors.min() >= 0 and cloud.colors.max() <= 1 and cloud.colors.std() > 0.05
    o3d = pytest.importorskip("open3d")
    reference = o3d.io.read_point_cloud(path)
    np.testing.assert_array_equal(np.asarray(reference.points), cloud.points)
    np.testing.assert_allclose(np.asarray(reference.colors), cloud.colors, atol=1e-12)
