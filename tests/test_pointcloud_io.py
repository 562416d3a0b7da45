"""Tests of the point-cloud readers and writers (PLY, PCD, .npy/.npz)."""

import os

import numpy as np
import pytest

import lieax.io as pcio

DATA_DIR = os.environ.get("LIEAX_DATA_DIR")

# A PCD written by Open3D 0.20 with `compressed=True`: 6 points (four of them equal, so the LZF
# stream holds back references) and packed uint32 colours.
OPEN3D_COMPRESSED_PCD = (
    b"# .PCD v0.7 - Point Cloud Data file format\nVERSION 0.7\nFIELDS x y z rgb\nSIZE 4 4 4 4\n"
    b"TYPE F F F U\nCOUNT 1 1 1 1\nWIDTH 6\nHEIGHT 1\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS 6\n"
    b"DATA binary_compressed\n9\x00\x00\x00`\x00\x00\x00\x01\x00\x00@\x00\x01\x80?\xe0\x01\x03\x01"
    b"\xc0\xbf\x80\x0b`\x00\x00@ \x05\xa0\x03\x01\x80>\xa0\x0b \x00\x00@ \x13\xc0\x03\x00\x80\xa0"
    b"\x0b\x00\xff\xc0\x02@\t\x03\x00\x80\x80\x80 \x07\x01\x00\x00"
)
COMPRESSED_POINTS = [[0, 0, 0], [1, 2, 3], [1, 2, 3], [1, 2, 3], [-1.5, 0.25, 4], [1, 2, 3]]
COMPRESSED_COLORS = [[1, 0, 0], [0, 1, 0], [0, 0, 1], [0, 0, 1], [128 / 255] * 3, [0, 0, 1]]


@pytest.fixture
def cloud():
    rng = np.random.default_rng(0)
    points = rng.normal(size=(50, 3))
    normals = rng.normal(size=(50, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    return points, normals, rng.uniform(size=(50, 3))


@pytest.mark.parametrize("binary", [True, False], ids=["binary", "ascii"])
def test_ply_round_trip(tmp_path, cloud, binary):
    points, normals, colors = cloud
    path = tmp_path / "cloud.ply"
    pcio.write_ply(path, points, normals, colors, binary=binary)
    read = pcio.read_point_cloud(path)
    np.testing.assert_allclose(read.points, points, rtol=1e-6, atol=1e-7)  # float32 in the file
    np.testing.assert_allclose(read.normals, normals, rtol=1e-6, atol=1e-7)
    np.testing.assert_allclose(read.colors, colors, atol=0.5 / 255 + 1e-12)
    assert read.points.dtype == np.float64 and set(read.fields) >= {"x", "nx", "red"}


@pytest.mark.parametrize("binary", [True, False], ids=["binary", "ascii"])
def test_pcd_round_trip(tmp_path, cloud, binary):
    points, normals, _ = cloud
    path = tmp_path / "cloud.pcd"
    pcio.write_pcd(path, points, normals, binary=binary)
    read = pcio.read_point_cloud(path, dtype=np.float32)
    np.testing.assert_allclose(read.points, points, rtol=1e-6, atol=1e-7)
    np.testing.assert_allclose(read.normals, normals, rtol=1e-6, atol=1e-7)
    assert read.colors is None and read.points.dtype == np.float32


def test_pcd_binary_compressed_from_open3d(tmp_path):
    path = tmp_path / "compressed.pcd"
    path.write_bytes(OPEN3D_COMPRESSED_PCD)
    read = pcio.read_pcd(path)
    np.testing.assert_array_equal(read.points, COMPRESSED_POINTS)
    np.testing.assert_allclose(read.colors, COMPRESSED_COLORS, atol=1e-12)


def test_ply_big_endian_with_other_elements(tmp_path):
    """A camera element before the vertices, faces after them, extra vertex properties."""
    points = np.array([[1.0, 2.0, 3.0], [-4.0, 5.5, 6.25], [0.0, 0.0, -1.0]])
    header = (
        "ply\nformat binary_big_endian 1.0\ncomment test\nelement camera 1\nproperty float view_px\n"
        "property uchar flag\nelement vertex 3\nproperty double x\nproperty double y\n"
        "property double z\nproperty ushort intensity\nelement face 1\n"
        "property list uchar int vertex_indices\nend_header\n"
    )
    record = np.dtype([("x", ">f8"), ("y", ">f8"), ("z", ">f8"), ("intensity", ">u2")])
    vertices = np.zeros(3, record)
    vertices["x"], vertices["y"], vertices["z"] = points.T
    vertices["intensity"] = [7, 8, 9]
    camera = np.array([(1.5, 3)], np.dtype([("view_px", ">f4"), ("flag", "u1")]))
    face = b"\x03" + np.array([0, 1, 2], ">i4").tobytes()
    path = tmp_path / "big.ply"
    path.write_bytes(header.encode() + camera.tobytes() + vertices.tobytes() + face)
    read = pcio.read_ply(path)
    np.testing.assert_array_equal(read.points, points)
    np.testing.assert_array_equal(read.fields["intensity"], [7, 8, 9])
    assert read.normals is None and read.colors is None


def test_ply_ascii_with_faces(tmp_path):
    path = tmp_path / "mesh.ply"
    path.write_text(
        "ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\n"
        "property float z\nelement face 1\nproperty list uchar int vertex_indices\nend_header\n"
        "0 0 0\n1 0 0\n0 1 0.5\n3 0 1 2\n"
    )
    np.testing.assert_array_equal(
        pcio.read_point_cloud(path).points, [[0, 0, 0], [1, 0, 0], [0, 1, 0.5]]
    )


def test_pcd_organized_with_padding_and_packed_rgb(tmp_path):
    """HEIGHT > 1 (flattened, NaN kept), a `_` padding field, a float-packed rgb, a uint field."""
    rgb = np.array([0x00FF8000, 0x000000FF, 0, 0x00FFFFFF], np.uint32).view(np.float32)
    record = np.dtype(
        [("x", "<f4"), ("y", "<f4"), ("z", "<f4"), ("_", "<f4"), ("rgb", "<f4"), ("ring", "<u2")]
    )
    rows = np.zeros(4, record)
    rows["x"] = [1, 2, np.nan, 4]
    rows["y"] = [0.5, 0.25, np.nan, 1]
    rows["z"] = [-1, -2, np.nan, 3]
    rows["rgb"] = rgb
    rows["ring"] = [0, 1, 2, 3]
    header = (
        "# .PCD v0.7\nVERSION 0.7\nFIELDS x y z _ rgb ring\nSIZE 4 4 4 4 4 2\nTYPE F F F F F U\n"
        "COUNT 1 1 1 1 1 1\nWIDTH 2\nHEIGHT 2\nVIEWPOINT 0 0 0 1 0 0 0\nPOINTS 4\nDATA binary\n"
    )
    path = tmp_path / "organized.pcd"
    path.write_bytes(header.encode() + rows.tobytes())
    read = pcio.read_pcd(path)
    assert read.points.shape == (4, 3) and np.all(np.isnan(read.points[2]))
    np.testing.assert_array_equal(read.points[[0, 1, 3]], [[1, 0.5, -1], [2, 0.25, -2], [4, 1, 3]])
    np.testing.assert_allclose(read.colors[0], [1.0, 128 / 255, 0.0])
    np.testing.assert_allclose(read.colors[1], [0.0, 0.0, 1.0])
    assert "_" not in read.fields and list(read.fields["ring"]) == [0, 1, 2, 3]


def test_numpy_arrays(tmp_path, cloud):
    points, normals, _ = cloud
    np.save(tmp_path / "points.npy", points)
    np.save(tmp_path / "both.npy", np.concatenate([points, normals], axis=1))
    np.savez(tmp_path / "pair.npz", source=points, target=points + 1)
    np.savez(tmp_path / "points.npz", points=points, other=np.zeros(3))
    np.testing.assert_array_equal(pcio.read_point_cloud(tmp_path / "points.npy").points, points)
    both = pcio.read_point_cloud(tmp_path / "both.npy")
    np.testing.assert_array_equal(both.normals, normals)
    np.testing.assert_array_equal(
        pcio.read_point_cloud(tmp_path / "pair.npz", key="target").points, points + 1
    )
    np.testing.assert_array_equal(pcio.read_point_cloud(tmp_path / "points.npz").points, points)
    with pytest.raises(ValueError, match="pass key="):
        pcio.read_point_cloud(tmp_path / "pair.npz")
    with pytest.raises(KeyError, match="no array 'normals'"):
        pcio.read_point_cloud(tmp_path / "pair.npz", key="normals")
    with pytest.raises(ValueError, match=r"shape \(n, 3\)"):
        pcio.read_point_cloud(tmp_path / "points.npz", key="other")


def test_errors(tmp_path):
    with pytest.raises(ValueError, match="Unknown point cloud format"):
        pcio.read_point_cloud(tmp_path / "cloud.xyz")
    (tmp_path / "bad.ply").write_bytes(b"plx\n")
    with pytest.raises(ValueError, match="not a PLY file"):
        pcio.read_ply(tmp_path / "bad.ply")
    (tmp_path / "short.ply").write_bytes(
        b"ply\nformat binary_little_endian 1.0\nelement vertex 10\nproperty float x\n"
        b"property float y\nproperty float z\nend_header\n" + bytes(12)
    )
    with pytest.raises(pcio.PointCloudFileError, match=r"short.ply: byte 116: .* ends after 12"):
        pcio.read_ply(tmp_path / "short.ply")
    (tmp_path / "noxyz.pcd").write_text(
        "VERSION 0.7\nFIELDS a b\nSIZE 4 4\nTYPE F F\nCOUNT 1 1\nWIDTH 1\nHEIGHT 1\nPOINTS 1\nDATA ascii\n1 2\n"
    )
    with pytest.raises(pcio.PointCloudFileError, match=r"noxyz.pcd:2: expected fields x, y, z"):
        pcio.read_pcd(tmp_path / "noxyz.pcd")
    with pytest.raises(ValueError, match=r"normals must have 50 rows"):
        pcio.write_ply(tmp_path / "x.ply", np.zeros((50, 3)), np.zeros((3, 3)))


@pytest.mark.skipif(DATA_DIR is None, reason="set LIEAX_DATA_DIR to the shared data")
def test_stanford_bunny_ply_matches_the_npz():
    folder = os.path.join(DATA_DIR, "clouds", "bunny_045_to_000")
    arrays = np.load(os.path.join(folder, "bunny_full.npz"))
    for name in ("source", "target"):
        read = pcio.read_point_cloud(os.path.join(folder, f"{name}.ply"))
        np.testing.assert_allclose(read.points, arrays[name], atol=1e-7)  # float32 in the PLY


# ---- LZF: the optional C decoder against the Python reference --------------------------------


def _lzf_compress(data):
    """A greedy LZF compressor (liblzf's format: literal runs of at most 32 bytes, back references
    of 3-264 bytes at most 8192 back, overlapping their own output where the match runs on) and
    the number of overlapping back references it wrote."""
    out, literal, table, overlapping = bytearray(), bytearray(), {}, 0
    i, n = 0, len(data)

    def flush():
        for start in range(0, len(literal), 32):
            run = literal[start : start + 32]
            out.append(len(run) - 1)
            out.extend(run)
        literal.clear()

    while i < n:
        key = bytes(data[i : i + 3])
        reference = table.get(key) if n - i >= 3 else None
        table[key] = i
        if reference is not None and i - reference <= 8192:
            length = 0
            while length < min(264, n - i) and data[reference + length] == data[i + length]:
                length += 1
            if length >= 3:
                flush()
                distance, code = i - reference - 1, length - 2
                overlapping += i - reference < length
                if code < 7:
                    out += bytes([(code << 5) | (distance >> 8), distance & 255])
                else:
                    out += bytes([(7 << 5) | (distance >> 8), code - 7, distance & 255])
                i += length
                continue
        literal.append(data[i])
        i += 1
    flush()
    return bytes(out), overlapping


def _lzf_samples():
    rng = np.random.default_rng(5)
    pieces = [rng.integers(0, 256, 700, dtype=np.uint8).tobytes(), bytes(3000), b"ab" * 400]
    pieces += [rng.integers(0, 4, 2000, dtype=np.uint8).tobytes(), b"xyz" * 5 + bytes(1)]
    cloud = np.repeat(rng.normal(size=(40, 3)).astype("<f4"), 7, axis=0).T.tobytes()
    return [b"".join(pieces), cloud, rng.integers(0, 256, 100, dtype=np.uint8).tobytes()]


def test_lzf_python_decoder_on_generated_streams():
    from lieax.io._lzf import lzf_decompress, lzf_decompress_python

    total_overlapping = 0
    for data in _lzf_samples():
        stream, overlapping = _lzf_compress(data)
        total_overlapping += overlapping
        assert len(stream) < len(data) or len(data) == 100
        assert lzf_decompress_python(stream, len(data), "s", 0) == data
        assert lzf_decompress(stream, len(data), "s", 0) == data
    assert total_overlapping > 10


def test_lzf_c_decoder_errors_are_located_by_the_python_decoder(monkeypatch):
    """The dispatch: a C result of the declared size is used; a refusal (or a short result) is
    re-decoded in Python, whose error names the chunk."""
    from lieax.io import _lzf

    data = _lzf_samples()[0]
    stream, _ = _lzf_compress(data)
    calls = []

    def fake(source, size):
        calls.append(size)
        return b"c" * size

    monkeypatch.setattr(_lzf, "_c_decompress", fake)
    assert _lzf.lzf_decompress(stream, len(data), "s", 0) == b"c" * len(data)
    for broken in (lambda source, size: None, lambda source, size: b"short"):
        monkeypatch.setattr(_lzf, "_c_decompress", broken)
        assert _lzf.lzf_decompress(stream, len(data), "s", 0) == data

    def refuse(source, size):
        raise ValueError("error in compressed data")

    monkeypatch.setattr(_lzf, "_c_decompress", refuse)
    with pytest.raises(pcio.PointCloudFileError, match=r"s: byte 7: LZF back reference 1 bytes"):
        _lzf.lzf_decompress(b"\x20\x00" + stream, len(data), "s", 7)
    assert calls == [len(data)]


def test_lzf_c_decoder_agrees_with_the_python_decoder():
    lzf = pytest.importorskip("lzf")
    from lieax.io._lzf import lzf_decompress_python

    streams = [(_lzf_compress(data)[0], len(data)) for data in _lzf_samples()]
    rng = np.random.default_rng(6)
    for _ in range(20):
        data = rng.integers(0, 3, int(rng.integers(1, 5000)), dtype=np.uint8).tobytes()
        streams += [(_lzf_compress(data)[0], len(data)), (lzf.compress(data), len(data))]
    if DATA_DIR and os.path.exists(os.path.join(DATA_DIR, "clouds/office_kinect/office1.pcd")):
        with open(os.path.join(DATA_DIR, "clouds/office_kinect/office1.pcd"), "rb") as handle:
            raw = handle.read()
        start = raw.index(b"DATA binary_compressed\n") + len(b"DATA binary_compressed\n")
        compressed, size = np.frombuffer(raw, "<u4", 2, start).tolist()
        streams.append((raw[start + 8 : start + 8 + compressed], size))
    for stream, size in streams:
        assert lzf.decompress(stream, size) == lzf_decompress_python(stream, size, "s", 0)
