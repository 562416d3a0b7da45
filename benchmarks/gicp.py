"""GICP benchmark: `lieax.icp.gicp` against small_gicp's `align(..., registration_type="GICP")`.

Same clouds (downsampled once, by lieax, and handed to both), covariances computed by each library
from 20 neighbours (small_gicp's default), the same `max_correspondence_distance` and iteration
cap (30), small_gicp with its default threads (one) and its default stopping rule (steps under
0.1° and 1 mm), lieax at its defaults (steps under 0.1° and 1e-3 max_correspondence_distance, or
fitness and RMSE changes under 1e-6) and at small_gicp's rule alone ("sg rule": 0.1°, 1 mm,
Open3D's tolerances 0). Every variant is compiled and warmed up, then timed interleaved with the
others (medians over rounds, wall clock). Iterations are updates made (small_gicp reports the
index of its last, one fewer: it is printed as reported).

Variants: each library's total (covariances of both clouds, k-d tree or index build, the
registration), and the registration alone with the covariances given (lieax in float64 and float32,
at its defaults, and in float64 at small_gicp's rule).

Clouds:
- the Stanford bunny at 2 mm and in full (reference: `bun.conf`'s `T_target_source`), 1 cm;
- the Kinect office frame registered against a moved copy of itself, resampled (2 cm voxels of
  an independent random half of the points) and cropped (reference: the known motion), 5 cm;
- `benchmarks/_scan_pairs.py`'s pairs of consecutive scans: the LiDAR scans (scan1 to scan0, 0.25 m
  voxels, 1 m; no reference: the gap to small_gicp) and the Kinect frame on a 1 cm and a 3 cm grid
  against an independently resampled, cropped, moved copy (reference: the known motion), three
  voxels.

Run `LIEAX_DATA_DIR=../shared/data python benchmarks/gicp.py` (needs the `bench` extra:
small_gicp). `--quick` runs the 2 mm bunny only, with fewer rounds.
"""

import argparse
import os
import sys

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

import jax

jax.config.update("jax_enable_x64", True)  # float64 variants; float32 ones pass float32 arrays

import _environment
import _scan_pairs
import jax.numpy as jnp
import numpy as np
import small_gicp
from _timing import (
    format_ratio,
    format_seconds,
    machine_description,
    markdown_table,
    time_interleaved,
)

import lieax
from lieax import SE3, icp

K = 20
MAX_ITERATIONS = 30


# ---- inputs -------------------------------------------------------------------------------------


def bunny(data_dir, name):
    data = np.load(os.path.join(data_dir, "clouds", "bunny_045_to_000", name))
    return data["source"], data["target"], data["T_target_source"]


def kinect(data_dir, voxel=0.02):
    """office1 (target, 2 cm voxels) and a copy moved by a known motion (5°, 5 cm), resampled from
    an independent random half of the raw points and cropped to 85% of its depth range (source)."""
    cloud = lieax.read_point_cloud(os.path.join(data_dir, "clouds", "office_kinect", "office1.pcd"))
    points = np.asarray(cloud.points)
    points = points[np.all(np.isfinite(points), axis=1)]
    target = np.asarray(icp.voxel_downsample(jnp.asarray(points), voxel))
    half = np.random.default_rng(0).random(len(points)) < 0.5
    resampled = np.asarray(icp.voxel_downsample(jnp.asarray(points[half]), voxel))
    depth = resampled[:, 2]
    resampled = resampled[depth < np.quantile(depth, 0.85)]
    tangent = np.concatenate([0.05 * np.array([0.6, -0.8, 0.0]), np.deg2rad(5.0) * np.array(
        [0.0, 0.6, 0.8])])  # fmt: skip
    truth = SE3.exp(jnp.asarray(tangent))
    source = np.asarray(truth.inverse() @ jnp.asarray(resampled))
    return source, target, np.asarray(truth.as_matrix())


def rotation_deg(a, b):
    r = a[:3, :3].T @ b[:3, :3]
    return float(np.degrees(np.arccos(np.clip((np.trace(r) - 1) / 2, -1, 1))))


def translation_gap(a, b):
    return float(np.linalg.norm(a[:3, 3] - b[:3, 3]))


# ---- runners ------------------------------------------------------------------------------------


def small_gicp_total(source, target, distance):
    def run():
        source_cloud, target_cloud = small_gicp.PointCloud(source), small_gicp.PointCloud(target)
        tree = small_gicp.KdTree(target_cloud)
        small_gicp.estimate_covariances(source_cloud, num_neighbors=K)
        small_gicp.estimate_covariances(target_cloud, tree, num_neighbors=K)
        return small_gicp.align(
            target_cloud, source_cloud, tree, registration_type="GICP",
            max_correspondence_distance=distance, max_iterations=MAX_ITERATIONS,
        )  # fmt: skip

    return run


def small_gicp_align(source, target, distance):
    source_cloud, target_cloud = small_gicp.PointCloud(source), small_gicp.PointCloud(target)
    tree = small_gicp.KdTree(target_cloud)
    small_gicp.estimate_covariances(source_cloud, num_neighbors=K)
    small_gicp.estimate_covariances(target_cloud, tree, num_neighbors=K)

    def run():
        return small_gicp.align(
            target_cloud, source_cloud, tree, registration_type="GICP",
            max_correspondence_distance=distance, max_iterations=MAX_ITERATIONS,
        )  # fmt: skip

    return run


def lieax_total(source, target, distance, dtype):
    s, t = jnp.asarray(source, dtype), jnp.asarray(target, dtype)

    def run():
        return icp.gicp(
            s, t, max_correspondence_distance=distance, max_iterations=MAX_ITERATIONS,
            covariances_k=K,
        )  # fmt: skip

    return run


def lieax_covariances(source, target, dtype):
    s, t = jnp.asarray(source, dtype), jnp.asarray(target, dtype)
    return lambda: (icp.estimate_covariances(s, k=K), icp.estimate_covariances(t, k=K))


SMALL_GICP_RULE = {
    "rotation_epsilon": np.deg2rad(0.1), "translation_epsilon": 1e-3, "relative_fitness": 0.0,
    "relative_rmse": 0.0,
}  # fmt: skip


def lieax_gicp(source, target, distance, dtype, rule=None):
    s, t = jnp.asarray(source, dtype), jnp.asarray(target, dtype)
    cs, ct = icp.estimate_covariances(s, k=K), icp.estimate_covariances(t, k=K)

    def run():
        return icp.gicp(
            s, t, source_covariances=cs, target_covariances=ct,
            max_correspondence_distance=distance, max_iterations=MAX_ITERATIONS, **(rule or {}),
        )  # fmt: skip

    return run


def covariances_agreeing(points):
    """The share of the points whose lieax covariance (k = 20) is within 1e-9 (every entry) of
    small_gicp's: the rest have their 20th and 21st nearest neighbours at the same distance (voxel
    grids, duplicated points), where either is right."""
    cloud = small_gicp.PointCloud(points)
    small_gicp.estimate_covariances(cloud, num_neighbors=K)
    theirs = np.asarray(cloud.covs())[:, :3, :3]
    ours = np.asarray(icp.estimate_covariances(jnp.asarray(points), k=K))
    return float(np.mean(np.max(np.abs(ours - theirs), axis=(1, 2)) < 1e-9))


def timed(run):
    """A zero-argument callable for `time_interleaved` (small_gicp returns no JAX arrays)."""
    return lambda: (run(), None)[1]


# ---- the table ----------------------------------------------------------------------------------


def case(label, source, target, reference, distance, rounds):
    variants = {
        "small_gicp total": timed(small_gicp_total(source, target, distance)),
        "small_gicp align": timed(small_gicp_align(source, target, distance)),
        "lieax total f64": lieax_total(source, target, distance, jnp.float64),
        "lieax covariances f64": lieax_covariances(source, target, jnp.float64),
        "lieax gicp f64": lieax_gicp(source, target, distance, jnp.float64),
        "lieax gicp f32": lieax_gicp(source, target, distance, jnp.float32),
        "lieax gicp f64 sg rule": lieax_gicp(
            source, target, distance, jnp.float64, SMALL_GICP_RULE
        ),
    }
    timings = time_interleaved(variants, rounds, warmup=1, min_sample_s=0)
    peer = small_gicp_total(source, target, distance)()
    peer_pose = np.asarray(peer.T_target_source)
    medians = {name: timing.median for name, timing in timings.items()}
    row = [
        label,
        f"{len(source)}/{len(target)}",
        format_seconds(medians["small_gicp total"]),
        format_seconds(medians["lieax total f64"]),
        format_ratio(medians["lieax total f64"], medians["small_gicp total"]),
        format_seconds(medians["small_gicp align"]),
        format_seconds(medians["lieax gicp f64"]),
        format_ratio(medians["lieax gicp f64"], medians["small_gicp align"]),
        format_seconds(medians["lieax gicp f32"]),
        format_ratio(medians["lieax gicp f32"], medians["small_gicp align"]),
        format_seconds(medians["lieax gicp f64 sg rule"]),
        format_ratio(medians["lieax gicp f64 sg rule"], medians["small_gicp align"]),
    ]
    accuracy = [label]
    for key in ("lieax gicp f64", "lieax gicp f32", "lieax gicp f64 sg rule"):
        result = variants[key]()
        pose = np.asarray(result.transform.as_matrix(), np.float64)
        accuracy.append(f"{int(result.iterations)} ({result.status_name.lower()})")
        if reference is None:
            accuracy.append(
                f"vs small_gicp {rotation_deg(pose, peer_pose):.3g}° / "
                f"{translation_gap(pose, peer_pose) * 1e3:.3g} mm"
            )
        else:
            accuracy.append(
                f"{rotation_deg(pose, reference):.3g}° / "
                f"{translation_gap(pose, reference) * 1e3:.3g} mm"
            )
    accuracy.insert(1, f"{peer.iterations} ({'converged' if peer.converged else 'not converged'})")
    accuracy.insert(
        2,
        "(reference)" if reference is None else
        f"{rotation_deg(peer_pose, reference):.3g}° / "
        f"{translation_gap(peer_pose, reference) * 1e3:.3g} mm",
    )  # fmt: skip
    gicp_result = variants["lieax gicp f64"]()
    iterations = max(int(gicp_result.iterations), 1)
    profile = [
        label,
        format_seconds(medians["lieax covariances f64"]),
        format_seconds(medians["lieax gicp f64"]),
        format_seconds(medians["lieax gicp f64"] / iterations),
        format_seconds(medians["small_gicp total"] - medians["small_gicp align"]),
        format_seconds(medians["small_gicp align"] / max(peer.iterations, 1)),
        f"{timings['lieax total f64'].compile_s - medians['lieax total f64']:.1f} s",
        f"{timings['lieax gicp f32'].compile_s - medians['lieax gicp f32']:.1f} s",
        f"{covariances_agreeing(source):.2%} / {covariances_agreeing(target):.2%}",
    ]
    return row, accuracy, profile


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    _environment.add_data_dir(parser)
    parser.add_argument("--rounds", type=int, default=7)
    parser.add_argument("--quick", action="store_true")
    parser.add_argument("--only", help="run the clouds whose label contains this (e.g. LiDAR)")
    args = parser.parse_args()
    cases = [("bunny 2 mm", lambda: bunny(args.data_dir, "bunny_v0.002.npz"), 0.01)]
    if not args.quick:
        cases += [
            ("bunny full", lambda: bunny(args.data_dir, "bunny_full.npz"), 0.01),
            ("Kinect 2 cm", lambda: kinect(args.data_dir), 0.05),
        ]
        for label, pair in _scan_pairs.scan_pairs(args.data_dir).items():
            cases.append((label, lambda p=pair: (p.source, p.target, p.truth), pair.distance))
    if args.only:
        cases = [c for c in cases if args.only.lower() in c[0].lower()]
    rounds = 3 if args.quick else args.rounds
    rows, accuracy, profile = [], [], []
    for label, load, distance in cases:
        source, target, reference = load()
        r, a, p = case(label, source, target, reference, distance, rounds)
        rows.append(r)
        accuracy.append(a)
        profile.append(p)
    print(f"{machine_description()}; {rounds} rounds; load average {os.getloadavg()[0]:.1f}")
    print()
    print(markdown_table(
        ["cloud", "points (source/target)", "small_gicp total", "lieax total f64", "ratio",
         "small_gicp align", "lieax gicp f64", "ratio", "lieax gicp f32", "ratio",
         "lieax gicp f64 sg rule", "ratio"], rows,
    ))  # fmt: skip
    print()
    print(markdown_table(
        ["cloud", "small_gicp iterations", "small_gicp error (rotation / translation)",
         "lieax f64 iterations", "lieax f64 error", "lieax f32 iterations", "lieax f32 error",
         "lieax sg rule iterations", "lieax sg rule error"],
        accuracy,
    ))  # fmt: skip
    print()
    print(markdown_table(
        ["cloud", "lieax covariances", "lieax registration", "lieax per iteration",
         "small_gicp covariances + tree", "small_gicp per iteration", "lieax compile f64 (total)",
         "lieax compile f32 (gicp)", "covariances equal to small_gicp's (source / target)"], profile,
    ))  # fmt: skip
    print(f"\nLoad average at the end: {os.getloadavg()[0]:.1f}")


if __name__ == "__main__":
    main()
