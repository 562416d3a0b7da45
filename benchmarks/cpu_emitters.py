"""XLA's classic CPU fusion emitters against its default ones, for the point-cloud programs.

`lieax._cpu_emitters.jit` compiles the ICP loop, the normals and the GICP covariances with
`xla_cpu_use_fusion_emitters=False`. This measures that choice in one process: each program run
with the option (`classic`) and without it (`default`, XLA's MLIR fusion emitters), interleaved,
warm medians, and XLA's compile time for each (the backend compilations of its first call: the
two variants share JAX's trace and lowering, the same program either way). On every
scan of `neighbors.load_clouds` (the bunny at 2 mm and in full, the LiDAR pair, the Kinect pair):

- `point_to_plane`: one registration from the identity, the target normals given (the host k-d
  tree rebuilt in every call);
- `gicp`: one registration, covariances estimated (the total);
- `estimate_normals` (k = 30) and `estimate_covariances` (k = 20) of the target.

Run `LIEAX_DATA_DIR=../shared/data python benchmarks/cpu_emitters.py [--rounds 7]`.
"""

import argparse
import os
import sys

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp
from jax import monitoring

from lieax import _cpu_emitters, icp
from lieax.icp import _host_kdtree

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

import _environment
import neighbors
from _timing import (
    format_ratio,
    format_seconds,
    machine_description,
    markdown_table,
    time_interleaved,
)
from icp import SCAN_NORMALS, scan_normals

KNOWN = _cpu_emitters.known
COMPILE_SECONDS = {"classic": 0.0, "default": 0.0}
_RUNNING = []


def _count_compile(event, seconds, **_):
    if event == "/jax/core/compile/backend_compile_duration" and _RUNNING:
        COMPILE_SECONDS[_RUNNING[-1]] += seconds


def programs(source, target, normals, radius):
    """The programs measured on one pair, each a zero-argument callable."""
    s, t, n = (jnp.asarray(x) for x in (source, target, normals))

    def fresh(run):  # (the host tree built in every call, as a new cloud would)
        def call():
            _host_kdtree._TREES.clear()
            _host_kdtree._IDS.clear()
            return run()

        return call

    return {
        "point_to_plane": fresh(
            lambda: icp.point_to_plane(s, t, target_normals=n, max_correspondence_distance=radius)
        ),
        "gicp": fresh(lambda: icp.gicp(s, t, max_correspondence_distance=radius)),
        "normals": fresh(lambda: icp.estimate_normals(t, k=30)),
        "covariances": fresh(lambda: icp.estimate_covariances(t, k=20)),
    }


def with_emitters(variant, run):
    def call():
        _cpu_emitters.known = KNOWN if variant == "classic" else (lambda: False)
        _RUNNING.append(variant)
        try:
            return run()
        finally:
            _RUNNING.pop()
            _cpu_emitters.known = KNOWN

    return call


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    _environment.add_data_dir(parser)
    parser.add_argument("--rounds", type=int, default=7)
    args = parser.parse_args()
    print(machine_description(), "\n")
    if not KNOWN():
        print("This XLA does not know xla_cpu_use_fusion_emitters: nothing to compare.")
        return
    monitoring.register_event_duration_secs_listener(_count_compile)
    rows = []
    for label, (source, target, radius, _) in neighbors.load_clouds(args.data_dir).items():
        normals = scan_normals(target, SCAN_NORMALS[label])
        for name, run in programs(source, target, normals, radius).items():
            variants = {name: with_emitters(name, run) for name in COMPILE_SECONDS}
            COMPILE_SECONDS.update(classic=0.0, default=0.0)
            timings = time_interleaved(variants, args.rounds, warmup=1, min_sample_s=0)
            classic, default = timings["classic"], timings["default"]
            rows.append([
                label, name, format_seconds(default.median), format_seconds(classic.median),
                format_ratio(classic.median, default.median),
                f"{COMPILE_SECONDS['default']:.2f} s", f"{COMPILE_SECONDS['classic']:.2f} s",
                format_ratio(COMPILE_SECONDS["classic"], COMPILE_SECONDS["default"]),
            ])  # fmt: skip
            print(" | ".join(rows[-1]), flush=True)
    headers = ["cloud", "program", "default emitters", "classic", "ratio", "XLA compile default",
               "XLA compile classic", "ratio"]  # fmt: skip
    print()
    print(markdown_table(headers, rows))


if __name__ == "__main__":
    main()
