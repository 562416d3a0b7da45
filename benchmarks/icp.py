"""ICP benchmark: `lieax.icp.point_to_plane` against Open3D's `registration_icp`.

Same clouds, same target normals (Open3D's `estimate_normals` with a 6 mm radius and 30
neighbours, handed to both), same `max_correspondence_distance` (1 cm), same iteration cap (30)
and convergence criteria (1e-6), Open3D with its default threading; every variant is compiled and
warmed up, then timed interleaved with the others (medians over rounds, wall clock). The lieax
wall time is one call of `point_to_plane`, including the build of its index on the target (Open3D
builds its k-d tree inside `registration_icp` too).

Tables:
1. One registration from the identity: the Stanford bunny at 2 mm (about 7k points) and in full
   (about 40k), lieax in float32 and float64; errors against the reference transform and against
   Open3D's result.
2. Growth with cloud size (both scans resampled to 10k, 40k, 160k and 640k points): compile
   time, the default search's phases (host k-d tree build, one matching step cold and warm, one
   Gauss-Newton step) and the totals.
3. Every kind of scan (`benchmarks/neighbors.py`'s clouds: the bunny at 2 mm and in full, 1 cm;
   outdoor LiDAR on a 0.5 m grid, 1 m; a Kinect frame on a 1 cm grid against a shifted-grid,
   cropped, moved copy, 5 cm; and `benchmarks/_scan_pairs.py`'s pairs of consecutive scans:
   LiDAR on a 0.25 m grid, 1 m; the Kinect frame on a 1 cm and a 3 cm grid against an
   independently resampled, cropped, moved copy, three voxels), `--only` choosing among them by
   label: Open3D against lieax with each `search` backend (`kdtree` is the default on a CPU),
   float64, Open3D's target normals given to both, Open3D's criteria 1e-6 / 30 and 1e-10 / 60;
   then the per-phase profile (index build, matching, normal equations) at the converged
   pose.

Run `LIEAX_DATA_DIR=../shared/data python benchmarks/icp.py` (needs the `bench` extra: open3d,
scipy; Open3D needs the system library libusb-1.0-0). `--quick` runs a small smoke version.
"""

import argparse
import functools
import os
import sys
import time

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import _environment

_environment.passive_openmp()  # before Open3D loads its OpenMP runtime

import jax

jax.config.update("jax_enable_x64", True)  # float64 variants; float32 ones pass float32 arrays

import jax.numpy as jnp
import numpy as np
import open3d as o3d
from _timing import (
    format_ratio,
    format_seconds,
    machine_description,
    markdown_table,
    time_interleaved,
)
from scipy.spatial import cKDTree

from lieax import SE3, icp
from lieax.icp import _coordinates, _host_kdtree, _plane_step, _search

MAX_DISTANCE = 0.01
MAX_ITERATIONS = 30
NORMALS_RADIUS, NORMALS_NN = 0.006, 30


# ---- inputs --------------------------------------------------------------------------------------


def load_pair(data_dir, name):
    data = np.load(os.path.join(data_dir, "clouds", "bunny_045_to_000", name))
    return data["source"], data["target"], data["T_target_source"]


def open3d_cloud(points, normals=None):
    cloud = o3d.geometry.PointCloud(o3d.utility.Vector3dVector(np.array(points, np.float64)))
    if normals is not None:
        cloud.normals = o3d.utility.Vector3dVector(np.array(normals, np.float64))
    return cloud


def open3d_normals(target):
    cloud = open3d_cloud(target)
    cloud.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(NORMALS_RADIUS, NORMALS_NN))
    return np.asarray(cloud.normals).copy()


def resample(points, count, seed):
    """`count` points on the scanned surface: a random subset, or (to grow) random points on the
    segments between a point and one of its 8 nearest neighbours."""
    rng = np.random.default_rng(seed)
    if count <= len(points):
        return points[rng.choice(len(points), count, replace=False)]
    _, neighbours = cKDTree(points).query(points, 9)
    base = rng.integers(0, len(points), count)
    other = neighbours[base, rng.integers(1, 9, count)]
    t = rng.uniform(0, 1, (count, 1))
    return points[base] + t * (points[other] - points[base])


def rotation_deg(a, b):
    r = a[:3, :3].T @ b[:3, :3]
    return float(np.degrees(np.arccos(np.clip((np.trace(r) - 1) / 2, -1, 1))))


def translation_gap(a, b):
    return float(np.linalg.norm(a[:3, 3] - b[:3, 3]))


# ---- runners -------------------------------------------------------------------------------------


def open3d_runner(source, target, normals):
    """`run(start=identity, cap=30)`: Open3D's point-to-plane ICP on these clouds."""
    source_cloud, target_cloud = open3d_cloud(source), open3d_cloud(target, normals)
    estimation = o3d.pipelines.registration.TransformationEstimationPointToPlane()

    def run(start=None, cap=MAX_ITERATIONS):
        criteria = o3d.pipelines.registration.ICPConvergenceCriteria(1e-6, 1e-6, cap)
        return o3d.pipelines.registration.registration_icp(
            source_cloud,
            target_cloud,
            MAX_DISTANCE,
            np.eye(4) if start is None else start,
            estimation,
            criteria,
        )

    return run


def lieax_runner(source, target, normals, dtype):
    s, t, n = (jnp.asarray(a, dtype) for a in (source, target, normals))

    def run():
        return icp.point_to_plane(s, t, target_normals=n, max_correspondence_distance=MAX_DISTANCE)

    return run


def open3d_iterations(run, full):
    """Open3D does not report its iteration count: the smallest cap that reproduces the result."""
    lo, hi = 1, MAX_ITERATIONS
    while lo < hi:
        mid = (lo + hi) // 2
        capped = np.asarray(run(cap=mid).transformation)  # threaded sums: equal up to rounding
        if np.allclose(capped, np.asarray(full.transformation), rtol=0, atol=1e-12):
            hi = mid
        else:
            lo = mid + 1
    return lo


def timed(run):
    """A zero-argument callable for `time_interleaved` (Open3D returns no JAX arrays)."""
    return lambda: (run(), None)[1]


# ---- 1. one registration ------------------------------------------------------------------------


def single(data_dir, rounds):
    rows, notes = [], []
    for name, label in (("bunny_v0.002.npz", "bunny 2 mm"), ("bunny_full.npz", "bunny full")):
        source, target, reference = load_pair(data_dir, name)
        extent = float(np.max(np.ptp(target, axis=0)))
        normals = open3d_normals(target)
        o3d_run = open3d_runner(source, target, normals)
        variants = {
            "open3d": timed(o3d_run),
            "lieax f32": lieax_runner(source, target, normals, jnp.float32),
            "lieax f64": lieax_runner(source, target, normals, jnp.float64),
        }
        timings = time_interleaved(variants, rounds, warmup=1, min_sample_s=0)
        full = o3d_run()
        o3d_pose = np.asarray(full.transformation)
        n_o3d = open3d_iterations(o3d_run, full)
        row = [label, f"{len(source)}/{len(target)}", format_seconds(timings["open3d"].median)]
        for key in ("lieax f32", "lieax f64"):
            result = variants[key]()
            pose = np.asarray(result.transform.as_matrix(), np.float64)
            row += [
                format_seconds(timings[key].median),
                format_ratio(timings[key].median, timings["open3d"].median),
            ]
            notes.append(
                f"{label}, {key}: compile {timings[key].compile_s:.1f} s; {int(result.iterations)} "
                f"iterations (Open3D {n_o3d}), {result.status_name}; fitness {float(result.fitness):.5f} "
                f"(Open3D {full.fitness:.5f}), RMSE {float(result.inlier_rmse) * 1e3:.4f} mm "
                f"(Open3D {full.inlier_rmse * 1e3:.4f} mm); vs reference {rotation_deg(pose, reference):.3f}° "
                f"/ {translation_gap(pose, reference) / extent:.2e} of the extent "
                f"(Open3D {rotation_deg(o3d_pose, reference):.3f}° / "
                f"{translation_gap(o3d_pose, reference) / extent:.2e}); vs Open3D "
                f"{rotation_deg(pose, o3d_pose):.5f}° / {translation_gap(pose, o3d_pose) / extent:.1e} of the extent"
            )
        rows.append(row)
    headers = [
        "cloud",
        "points (source/target)",
        "Open3D",
        "lieax f32",
        "ratio",
        "lieax f64",
        "ratio",
    ]
    return markdown_table(headers, rows), notes


# ---- 2. growth with cloud size ------------------------------------------------------------------


def growth(data_dir, sizes, rounds):
    source, target, reference = load_pair(data_dir, "bunny_full.npz")
    rows = []
    for size in sizes:
        s_np, t_np = resample(source, size, 1), resample(target, size, 2)
        normals = open3d_normals(t_np)
        o3d_run = open3d_runner(s_np, t_np, normals)
        lieax_run = lieax_runner(s_np, t_np, normals, jnp.float32)
        parts = component_timings(s_np, t_np, normals, reference, rounds)
        timings = time_interleaved(
            {"open3d": timed(o3d_run), "lieax": lieax_run}, rounds, warmup=1, min_sample_s=0
        )
        result = lieax_run()
        full = o3d_run()
        n_o3d = open3d_iterations(o3d_run, full)
        rows.append([
            f"{size // 1000}k",
            f"{timings['lieax'].compile_s:.1f} s",
            format_seconds(parts["build"]),
            format_seconds(parts["cold match"]),
            format_seconds(parts["warm match"]),
            format_seconds(parts["step"]),
            f"{int(result.iterations)} / {n_o3d}",
            format_seconds(timings["open3d"].median / n_o3d),
            format_seconds(timings["lieax"].median),
            format_seconds(timings["open3d"].median),
            format_ratio(timings["lieax"].median, timings["open3d"].median),
        ])  # fmt: skip
    headers = [
        "points", "lieax compile", "index build", "match / it. (cold)", "match / it. (warm)",
        "GN step / it.",
        "iterations (lieax / Open3D)", "Open3D / it.", "lieax total", "Open3D total", "ratio",
    ]  # fmt: skip
    return markdown_table(headers, rows)


def component_timings(source, target, normals, reference, rounds):
    """Seconds for the pieces of one registration with the default search (the host k-d tree,
    pykdtree), at the reference pose (float32): index build (a fresh tree), one matching step with
    every query sent to the tree (a cold one, as after a large move) and one warm-started from the
    converged matches (as near convergence), and one Gauss-Newton step (normal equations and
    solve)."""
    import neighbors

    s, t, n = (jnp.asarray(a, jnp.float32) for a in (source, target, normals))
    params = SE3.from_matrix(jnp.asarray(reference, jnp.float32)).parameters()
    build = neighbors.builder("kdtree pykdtree", MAX_DISTANCE)
    index = build(t)
    queries = _coordinates.transform_points(params, s)
    cold = neighbors.matcher("kdtree", MAX_DISTANCE, warm=False)
    warm = neighbors.matcher("kdtree", MAX_DISTANCE)
    slot, d2 = cold(index, queries, None)
    inliers = d2 <= MAX_DISTANCE**2
    normals_slots = n[index.order]
    step = jax.jit(
        lambda p, m, w: _plane_step.plane_step(
            p, s, None, index.points[m], normals_slots[m], w, lambda x: jnp.ones_like(x)
        )
    )
    variants = {
        "build": lambda: neighbors.fresh_build(build, t),
        "cold match": lambda: cold(index, queries, None),
        "warm match": lambda: warm(index, queries, slot),
        "step": lambda: step(params, slot, inliers),
    }
    timings = time_interleaved(variants, rounds, warmup=1)
    return {key: timing.median for key, timing in timings.items()}


# ---- 3. every kind of scan ----------------------------------------------------------------------

SCAN_NORMALS = {"bunny 2 mm": 0.006, "bunny full": 0.006, "LiDAR": 1.5, "Kinect": 0.03}
SCAN_SEARCHES = "grid,kdtree"


def scan_clouds(data_dir, only=None):
    """`{label: (source, target, max distance, T_target_source or None, normals radius)}`:
    `neighbors.load_clouds`' scans and `_scan_pairs`' pairs (the labels containing `only`)."""
    import _scan_pairs
    import neighbors

    clouds = {
        label: (*cloud, SCAN_NORMALS[label])
        for label, cloud in neighbors.load_clouds(data_dir).items()
    }
    for label, pair in _scan_pairs.scan_pairs(data_dir).items():
        clouds[label] = (pair.source, pair.target, pair.distance, pair.truth, pair.normals_radius)
    return {k: v for k, v in clouds.items() if only is None or only.lower() in k.lower()}


def scan_normals(target, radius):
    """Open3D's normals of a scan's target (`radius`, at most 30 neighbours), the ones handed to
    both libraries."""
    cloud = open3d_cloud(target)
    cloud.estimate_normals(o3d.geometry.KDTreeSearchParamHybrid(radius, 30))
    return np.asarray(cloud.normals).copy()


def scans(data_dir, rounds, criteria, searches, only=None):
    """One registration per scan (`scan_clouds`), Open3D against lieax with each search backend
    (float64, Open3D's target normals given to both), for each `(tolerance, cap)`."""
    rows, notes, profiles = [], [], []
    for label, (source, target, radius, truth, normals_radius) in scan_clouds(
        data_dir, only
    ).items():
        normals = scan_normals(target, normals_radius)
        clouds = (source, target, normals, radius, truth)
        for tolerance, cap in criteria:
            row, row_notes = scan_row(label, clouds, tolerance, cap, rounds, searches)
            rows.append(row)
            notes += row_notes
        profiles.append([label, "kdtree", *scan_profile("kdtree", clouds, rounds)])
    headers = ["cloud", "points (source/target)", "distance", "criteria", "Open3D"] + [
        f"lieax {name} (ratio)" for name in searches
    ]
    profile_headers = ["cloud", "search", "index build", "match / it.", "normal equations / it."]
    return markdown_table(headers, rows), notes, markdown_table(profile_headers, profiles)


def scan_row(label, clouds, tolerance, cap, rounds, searches):
    source, target, normals, radius, truth = clouds
    source_cloud, target_cloud = open3d_cloud(source), open3d_cloud(target, normals)
    estimation = o3d.pipelines.registration.TransformationEstimationPointToPlane()
    settings = o3d.pipelines.registration.ICPConvergenceCriteria(tolerance, tolerance, cap)
    s, t, n = (jnp.asarray(x) for x in (source, target, normals))

    def o3d_run():
        return o3d.pipelines.registration.registration_icp(
            source_cloud, target_cloud, radius, np.eye(4), estimation, settings
        )

    def lieax_run(search):
        return icp.point_to_plane(
            s, t, target_normals=n, max_correspondence_distance=radius, search=search,
            relative_fitness=tolerance, relative_rmse=tolerance, max_iterations=cap,
        )  # fmt: skip

    def fresh_run(search):  # the host tree rebuilt in every call, as Open3D's
        _host_kdtree._TREES.clear()
        _host_kdtree._IDS.clear()
        return lieax_run(search)

    variants = {"open3d": timed(o3d_run)}
    variants.update({name: functools.partial(fresh_run, name) for name in searches})
    timings = time_interleaved(variants, rounds, warmup=1, min_sample_s=0)
    full = o3d_run()
    o3d_pose = np.asarray(full.transformation)
    row = [label, f"{len(source)}/{len(target)}", f"{radius:g} m", f"{tolerance:g} / {cap}",
           format_seconds(timings["open3d"].median)]  # fmt: skip
    notes = []
    for name in searches:
        result = variants[name]()
        pose = np.asarray(result.transform.as_matrix(), np.float64)
        ratio = format_ratio(timings[name].median, timings["open3d"].median)
        row.append(f"{format_seconds(timings[name].median)} ({ratio})")
        truth_gap = "" if truth is None else f"; vs truth {rotation_deg(pose, truth):.4f}°"
        notes.append(
            f"{label}, {tolerance:g}/{cap}, {name}: compile {timings[name].compile_s:.1f} s, "
            f"{int(result.iterations)} iterations, {result.status_name}, fitness "
            f"{float(result.fitness):.4f} (Open3D {full.fitness:.4f}); vs Open3D "
            f"{rotation_deg(pose, o3d_pose):.4f}° / {translation_gap(pose, o3d_pose):.1e} m"
            f"{truth_gap}"
        )
    return row, notes


def scan_profile(name, clouds, rounds):
    """Per-phase seconds at the converged pose, float64, for one backend: index build, one
    matching step (warm-started from the converged matches), one Gauss-Newton step (normal
    equations and solve)."""
    import neighbors

    source, target, normals, radius, truth = clouds
    queries = jnp.asarray(neighbors.aligned(source, target, radius, truth))
    s, t = jnp.asarray(source), jnp.asarray(target)
    build, match = neighbors.builder(name, radius), neighbors.matcher(name, radius)
    index = build(t)
    slot, d2 = match(index, queries, _search.nearest(index, queries, radius=radius).slot)
    inliers = d2 <= radius**2
    matched_normals = jnp.asarray(normals)[index.order]
    step = jax.jit(
        lambda p, sl, w: _plane_step.plane_step(
            p, s, None, index.points[sl], matched_normals[sl], w, lambda x: jnp.ones_like(x)
        )
    )
    params = jnp.asarray([1.0, 0, 0, 0, 0, 0, 0])
    variants = {
        "build": lambda: neighbors.fresh_build(build, t),
        "match": lambda: match(index, queries, slot),
        "step": lambda: step(params, slot, inliers),
    }
    timings = time_interleaved(variants, rounds, warmup=1)
    return [
        format_seconds(timings[k].median) if k in timings else "—"
        for k in ("build", "match", "step")
    ]


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    _environment.add_data_dir(parser)
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--sizes", default="10000,40000,160000,640000")
    parser.add_argument("--quick", action="store_true", help="2 rounds, 10k only")
    parser.add_argument("--searches", default=SCAN_SEARCHES, help="backends in the scans table")
    parser.add_argument(
        "--skip", default="",
        help="comma-separated sections to skip: single,growth,scans",
    )  # fmt: skip
    parser.add_argument("--only", help="in the scans table, the clouds whose label contains this")
    args = parser.parse_args()
    if args.quick:
        args.rounds, args.sizes = 2, "10000"
    skip = set(filter(None, args.skip.split(",")))
    print(f"# ICP benchmark\n\n{machine_description()}, Open3D {o3d.__version__}, "
          f"{os.cpu_count()} CPUs; {time.strftime('%Y-%m-%d %H:%M')}, load average "
          f"{os.getloadavg()[0]:.1f}\n")  # fmt: skip
    if "single" not in skip:
        table, notes = single(args.data_dir, args.rounds)
        print("## One registration from the identity\n\n" + table + "\n")
        print("\n".join(f"- {note}" for note in notes) + "\n")
    if "growth" not in skip:
        sizes = [int(s) for s in args.sizes.split(",")]
        print(
            "## Growth with cloud size (float32, resampled full bunny)\n\n"
            + growth(args.data_dir, sizes, args.rounds)
            + "\n"
        )
    if "scans" not in skip:
        criteria = [(1e-6, 30)] if args.quick else [(1e-6, 30), (1e-10, 60)]
        searches = args.searches.split(",")
        rounds = max(2, args.rounds // 2)
        table, notes, profile = scans(args.data_dir, rounds, criteria, searches, args.only)
        print("## Every kind of scan (float64; lieax time and ratio to Open3D)\n\n" + table + "\n")
        print("\n".join(f"- {note}" for note in notes) + "\n")
        print("### Per-phase profile at the converged pose (float64)\n\n" + profile + "\n")
        print(f"Load average at the end: {os.getloadavg()[0]:.1f}\n")


if __name__ == "__main__":
    main()
