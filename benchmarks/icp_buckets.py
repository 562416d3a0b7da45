"""Capacity buckets: what a new cloud size costs with and without them.

A LiDAR stream feeds clouds of a new size every frame. With `buckets=True` (the default) ICP pads
them to one of four sizes per doubling (`lieax.icp._batch.bucket_size`), so a new size inside a
known bucket reuses the compiled loop and normals; `buckets=False` compiles for every shape.

Measured in one process, in this order (wall clock, trace + compile + run, point-to-plane from
the identity with the target normals estimated, 1 m distance):

1. `buckets=True`, scan0 to scan1 (24,989 and 25,193 points; both in the 28,672 bucket): first call.
2. `buckets=True`, random subsets of 24,700 and 25,000 points: a new size in the same buckets;
   then the same call again (the run alone, nothing traced or compiled).
3. `buckets=False`, the same subsets: a new shape, compiled; then again (the cost of the padded
   rows is the difference between the two warm calls).
4. `buckets=False`, scan0 to scan1 again: the shape of 3 is not reused by 1's loop either.

Then a stream of 20 synthetic pairs of 3000 to 4500 points: compilations of the loop counted.

Run `LIEAX_DATA_DIR=../shared/data python benchmarks/icp_buckets.py`.
"""

import os
import time

import jax

jax.config.update("jax_enable_x64", True)

import numpy as np

from lieax import icp
from lieax.icp import _loop
from lieax.icp._batch import bucket_size


def timed(source, target, buckets):
    start = time.perf_counter()
    result = icp.point_to_plane(source, target, max_correspondence_distance=1.0, buckets=buckets)
    result.transform.parameters().block_until_ready()
    return time.perf_counter() - start, result


def main():
    data = np.load(os.path.join(os.environ["LIEAX_DATA_DIR"], "clouds", "lidar_scans_0_1_2",
                                "scans.npz"))  # fmt: skip
    scan0, scan1 = data["scan0"], data["scan1"]
    rng = np.random.default_rng(0)
    sub0 = scan0[rng.choice(len(scan0), 24_700, replace=False)]
    sub1 = scan1[rng.choice(len(scan1), 25_000, replace=False)]
    rows = []
    for label, (source, target), buckets in (
        ("first call", (scan0, scan1), True),
        ("new size, same bucket", (sub0, sub1), True),
        ("the same call again (warm)", (sub0, sub1), True),
        ("new size, buckets=False", (sub0, sub1), False),
        ("the same call again (warm), buckets=False", (sub0, sub1), False),
        ("another size, buckets=False", (scan0, scan1), False),
    ):
        seconds, result = timed(source, target, buckets)
        shapes = f"{len(source)} → {bucket_size(len(source)) if buckets else len(source)}"
        rows.append((label, shapes, seconds, result.status_name, float(result.fitness)))
    print("| call | source rows (padded) | time | status | fitness |")
    print("|---|---|---|---|---|")
    for label, shapes, seconds, status, fitness in rows:
        print(f"| {label} | {shapes} | {seconds:.2f} s | {status} | {fitness:.4f} |")

    sizes = rng.integers(3000, 4501, size=20)
    loops = _loop.solve._cache_size()
    start = time.perf_counter()
    for k, n in enumerate(sizes):
        source, target, normals, _ = icp.synthetic_pair(int(n), seed=k)
        icp.point_to_plane(source, target, target_normals=normals, max_correspondence_distance=0.2)
    print(f"\n20 synthetic pairs of 3000-4500 points ({len(set(sizes))} sizes, "
          f"{len({bucket_size(int(n)) for n in sizes})} buckets): "
          f"{_loop.solve._cache_size() - loops} compilations of the loop, "
          f"{time.perf_counter() - start:.1f} s in all")  # fmt: skip


if __name__ == "__main__":
    main()
