"""Reading an LZF-compressed (`binary_compressed`) PCD: `lieax.io.read_pcd` with its pure-Python
LZF decoder and, when the optional package `python-lzf` is installed, with liblzf's C decoder,
against Open3D's `read_point_cloud` (and the LZF decoders alone), in one process, interleaved,
medians after warm-up.

The cloud is PCL's `office1.pcd` (640×480, x y z rgb, 1.9 MB compressed to 4.9 MB) from
`LIEAX_DATA_DIR`, else a cloud of the same size written by Open3D with `compressed=True`
(needs open3d). Run `LIEAX_DATA_DIR=../shared/data python benchmarks/pcd_read.py` (the `bench`
extra; `pip install python-lzf` for the C decoder). `--rounds N` sets the rounds (default 7).
"""

import argparse
import os
import sys
import tempfile

import numpy as np

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

from _timing import format_ratio, format_seconds, markdown_table, time_interleaved

from lieax.io import _lzf, read_pcd

OFFICE = "clouds/office_kinect/office1.pcd"


def _cloud_path(directory):
    data_dir = os.environ.get("LIEAX_DATA_DIR")
    if data_dir and os.path.exists(os.path.join(data_dir, OFFICE)):
        return os.path.join(data_dir, OFFICE), "office1.pcd"
    import open3d as o3d

    rng = np.random.default_rng(0)
    u, v = np.meshgrid(np.arange(640), np.arange(480))
    depth = 1.5 + 0.5 * np.sin(u / 60.0) * np.cos(v / 45.0) + rng.normal(0, 1e-3, u.shape)
    points = np.stack([(u - 320) / 525 * depth, (v - 240) / 525 * depth, depth], -1)
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(points.reshape(-1, 3)))
    cloud.colors = o3d.utility.Vector3dVector(rng.uniform(size=(640 * 480, 3)).round(1))
    path = os.path.join(directory, "generated.pcd")
    o3d.io.write_point_cloud(path, cloud, compressed=True)
    return path, "generated 640×480 (Open3D, compressed)"


def _compressed_stream(path):
    with open(path, "rb") as handle:
        raw = handle.read()
    start = raw.index(b"DATA binary_compressed\n") + len(b"DATA binary_compressed\n")
    compressed, size = np.frombuffer(raw, "<u4", 2, start).tolist()
    return raw[start + 8 : start + 8 + compressed], size


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rounds", type=int, default=7)
    args = parser.parse_args()
    c_decoder = _lzf._c_decompress
    with tempfile.TemporaryDirectory() as directory:
        path, name = _cloud_path(directory)
        stream, size = _compressed_stream(path)

        def lieax_python():
            _lzf._c_decompress = None
            try:
                return read_pcd(path).points
            finally:
                _lzf._c_decompress = c_decoder

        variants = {"lieax read_pcd, Python LZF": lieax_python}
        if c_decoder is not None:
            variants["lieax read_pcd, C LZF (python-lzf)"] = lambda: read_pcd(path).points
        try:
            import open3d as o3d

            variants["Open3D read_point_cloud"] = lambda: np.asarray(
                o3d.io.read_point_cloud(path).points
            )
        except ImportError:
            pass
        variants["LZF alone, Python"] = lambda: _lzf.lzf_decompress_python(stream, size, path, 0)
        if c_decoder is not None:
            variants["LZF alone, C (python-lzf)"] = lambda: c_decoder(stream, size)
        timings = time_interleaved(variants, args.rounds, warmup=1, max_variant_s=60.0)
    reference = timings["lieax read_pcd, Python LZF"].median
    print(f"{name}: {len(stream) / 1e6:.2f} MB of LZF to {size / 1e6:.2f} MB; medians of "
          f"{args.rounds} interleaved rounds (a shared machine: compare the ratios)\n")  # fmt: skip
    rows = [
        [variant, format_seconds(t.median), format_ratio(t.median, reference)]
        for variant, t in timings.items()
    ]
    print(markdown_table(["variant", "median", "vs lieax Python"], rows))


if __name__ == "__main__":
    main()
