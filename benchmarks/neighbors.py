"""Nearest-neighbour backends side by side on every kind of scan (`lieax.icp._search`).

Clouds (the ICP benchmark's, `benchmarks/icp.py` imports them from here):
- bunny 2 mm and bunny full: the Stanford bunny pair (object scans), 1 cm radius;
- LiDAR: outdoor Velodyne scans 1 -> 0 (`lidar_scans_0_1_2/scans.npz`), on a voxel grid, 1 m radius;
- Kinect: `office_kinect/office1.pcd` on a 1 cm voxel grid (the target) against a copy resampled
  on a grid shifted by half a voxel, cropped, and moved by a known motion (the source), 5 cm.

Per cloud and backend, at the pose ICP converges to: the index build (jitted, on the target; the
host tree's registry emptied first), one matching step of every source point inside a jitted call
from scratch and warm-started from the exact matches (the host trees skipping the matches their
spacing test keeps; the native tree, which keeps no spacing, answering every query), and
exactness: the share of the source points with a target point within the radius that got their
nearest one (or one at the same distance) in the warm-started step, against SciPy's cKDTree. The
two host libraries are also timed bare (numpy in, numpy out) to choose between them.

A third table, `--libraries`, compares the k-d trees lieax could use: SciPy's cKDTree
(`balanced_tree=False`, as lieax builds it), pykdtree, small_gicp's `KdTree` and lieax's native
tree (`lieax.icp._native_kdtree`, each call a jitted custom call), float64, built on
the target and queried for k = 1 (the source at the converged pose: ICP's matching) and k = 10
(the target against itself: normals and covariances), no distance bound (small_gicp has none),
each with its default threads (cKDTree `workers=1`, pykdtree OpenMP's default: one per core,
small_gicp `num_threads=1`, native one per core) and with the other choice (one thread for
pykdtree, by threadpoolctl, and the native tree, by `lieax.threads`; one per core for cKDTree and
small_gicp), also on the raw
25k-point LiDAR scans; medians of interleaved repeats.

Run `LIEAX_DATA_DIR=../shared/data python benchmarks/neighbors.py` (needs the `bench` extra:
open3d, small_gicp). `--quick`: fewer rounds, no brute force on large targets. `--libraries`:
only the host trees' table.
"""

import argparse
import os
import sys
import time

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp
import numpy as np
from scipy.spatial import cKDTree

from lieax.icp import _host_kdtree, _search

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

import _environment
import _scan_pairs
from _timing import format_seconds, machine_description, markdown_table, time_interleaved

LIDAR_VOXEL = 0.5
KINECT_VOXEL = 0.01
BACKENDS = ("grid", "kdtree native", "kdtree pykdtree", "kdtree scipy", "brute")


# ---- clouds --------------------------------------------------------------------------------------


def load_clouds(data_dir):
    """`{label: (source, target, radius, T_target_source or None)}` (float64 numpy)."""
    clouds = {}
    for name, label in (("bunny_v0.002.npz", "bunny 2 mm"), ("bunny_full.npz", "bunny full")):
        data = np.load(os.path.join(data_dir, "clouds", "bunny_045_to_000", name))
        clouds[label] = (data["source"], data["target"], 0.01, data["T_target_source"])
    lidar = _scan_pairs.lidar_pair(data_dir, voxel=LIDAR_VOXEL, distance=1.0)
    clouds["LiDAR"] = (lidar.source, lidar.target, lidar.distance, None)
    kinect = _scan_pairs.kinect_pair(
        _scan_pairs.kinect_points(data_dir), KINECT_VOXEL, 0.05, keep=1.0, crop=0.2, degrees=3.0,
        translation=0.05, seed=5,
    )  # fmt: skip
    clouds["Kinect"] = (kinect.source, kinect.target, kinect.distance, kinect.truth)
    return clouds


def aligned(source, target, radius, truth):
    """The source at the pose ICP converges to: the known motion, or (LiDAR) SciPy-matched
    point-to-point ICP from the identity."""
    if truth is not None:
        return source @ truth[:3, :3].T + truth[:3, 3]
    tree, moved = cKDTree(target), source
    for _ in range(30):
        distance, nearest = tree.query(moved, distance_upper_bound=radius)
        ok = np.isfinite(distance)
        a, b = moved[ok], target[nearest[ok]]
        ca, cb = a.mean(0), b.mean(0)
        u, _, vt = np.linalg.svd((b - cb).T @ (a - ca))
        rotation = u @ np.diag([1, 1, np.sign(np.linalg.det(u @ vt))]) @ vt
        moved = (moved - ca) @ rotation.T + cb
    return moved


# ---- one cloud ----------------------------------------------------------------------------------


def builder(backend, radius):
    name, _, library = backend.partition(" ")
    options = {"library": library} if name == "kdtree" and library else {}
    return jax.jit(lambda t: _search.build_index(t, search=name, max_distance=radius, **options))


def matcher(backend, radius, warm=True):
    """`match(index, queries, slot)`, one ICP matching step: the host tree warm-started from
    `slot` (with `warm`); the others' exact search."""
    previous = backend.startswith("kdtree") and warm
    return jax.jit(
        lambda index, q, slot: _search.match(index, q, radius, previous=slot if previous else None)
    )


def fresh_build(build, t):
    """`build(t)` with the host registry emptied (it would find the tree built before), then
    restored (indexes in use keep their trees)."""
    trees, ids = dict(_host_kdtree._TREES), dict(_host_kdtree._IDS)
    _host_kdtree._TREES.clear()
    _host_kdtree._IDS.clear()
    index = jax.block_until_ready(build(t))
    _host_kdtree._TREES.update(trees)
    _host_kdtree._IDS.update(ids)
    return index


def exact_share(found_distance, reference_distance, radius):
    within = reference_distance <= radius
    same = np.isclose(found_distance, reference_distance, rtol=1e-6, atol=1e-7)
    return np.mean(same[within]), np.mean(within)


def measure(label, source, target, radius, truth, rounds, dtype, skip_brute_above):
    queries_np = aligned(source, target, radius, truth)
    reference, _ = cKDTree(target).query(queries_np)
    t, q = jnp.asarray(target, dtype), jnp.asarray(queries_np, dtype)
    rows = []
    for backend in BACKENDS:
        if backend == "brute" and len(target) > skip_brute_above:
            rows.append([label, backend, "—", "—", "—", "skipped (`--quick`)"])
            continue
        row, within = measure_backend(backend, t, q, reference, radius, rounds)
        rows.append([label, *row])
    return rows, within


def measure_backend(backend, t, q, reference, radius, rounds):
    build, cold = builder(backend, radius), matcher(backend, radius, warm=False)
    warm = matcher(backend, radius)
    index = build(t)
    # The converged matches: where the warm host tree starts from.
    slot = _search.nearest(index, q, radius=radius).slot
    variants = {"build": lambda: fresh_build(build, t), "cold": lambda: cold(index, q, slot)}
    if backend.startswith("kdtree"):
        variants["warm"] = lambda: warm(index, q, slot)
    timings = time_interleaved(variants, rounds, warmup=1)
    _, found_d2 = warm(index, q, slot)
    share, within = exact_share(np.sqrt(np.asarray(found_d2, np.float64)), reference, radius)
    note = f"{share:.2%}"
    times = [
        format_seconds(timings[k].median) if k in timings else "—"
        for k in ("build", "cold", "warm")
    ]
    return [backend, *times, note], within


def host_libraries(label, source, target, radius, truth, repeats=7):
    """Bare build and query times of cKDTree (1 and 2 workers) and pykdtree, numpy arrays."""
    from pykdtree.kdtree import KDTree

    def median(fn, *args, **kwargs):
        times = []
        for _ in range(repeats):
            start = time.perf_counter()
            fn(*args, **kwargs)
            times.append(time.perf_counter() - start)
        return format_seconds(np.median(times))

    queries = aligned(source, target, radius, truth)
    row = [label]
    for dtype in (np.float64, np.float32):
        t, q = target.astype(dtype), queries.astype(dtype)
        scipy_tree, pyk_tree = cKDTree(t, balanced_tree=False), KDTree(t)
        row += [
            median(cKDTree, t, balanced_tree=False),
            median(scipy_tree.query, q, 1, distance_upper_bound=radius),
            median(scipy_tree.query, q, 1, distance_upper_bound=radius, workers=2),
            median(KDTree, t),
            median(pyk_tree.query, q, 1, distance_upper_bound=radius),
        ]
    return row


# (library, threads): None is the library's default (cKDTree and small_gicp: one thread; pykdtree:
# OpenMP's, one per core), a number that many threads
HOST_TREES = (
    ("cKDTree", None), ("cKDTree", os.cpu_count()), ("pykdtree", None), ("pykdtree", 1),
    ("small_gicp", None), ("small_gicp", os.cpu_count()), ("native", None), ("native", 1),
)  # fmt: skip


def host_tree_variants(target, queries, library, threads):
    """`{what: zero-argument callable}` building `library`'s tree of `target` and querying it for
    k = 1 (`queries`) and k = 10 (the target itself) on `threads` threads (None: its default;
    pykdtree's OpenMP pool limited through one threadpoolctl controller made here, since a fresh
    `threadpool_limits` lists the process's libraries at every call: about 1 ms)."""
    import small_gicp
    from pykdtree.kdtree import KDTree
    from threadpoolctl import ThreadpoolController

    if library == "native":
        return native_tree_variants(target, queries, threads)
    if library == "cKDTree":
        workers = 1 if threads is None else threads
        build = lambda: cKDTree(target, balanced_tree=False)
        query = lambda tree, q, k: tree.query(q, k, workers=workers)
    elif library == "pykdtree":
        build = lambda: KDTree(target)
        query = lambda tree, q, k: tree.query(q, k)
    else:
        count = 1 if threads is None else threads
        build = lambda: small_gicp.KdTree(target, num_threads=count)
        query = lambda tree, q, k: tree.batch_knn_search(q, k, num_threads=count)
    tree = build()
    variants = {
        "build": build,
        "k=1": lambda: query(tree, queries, 1),
        "k=10": lambda: query(tree, target, 10),
    }
    if library == "pykdtree" and threads is not None:
        openmp = ThreadpoolController().select(user_api="openmp")

        def limited(fn):
            def run():
                with openmp.limit(limits=threads):
                    return fn()

            return run

        variants = {what: limited(fn) for what, fn in variants.items()}
    return variants


def native_tree_variants(target, queries, threads):
    """`host_tree_variants` of lieax's native tree (`lieax.icp._native_kdtree`), each a jitted
    call of its custom call, NumPy in and out (`threads`: None, one per core, or that many by
    `lieax.threads`). Its k = 10 query of the target is `neighbours`, which builds the tree in
    the same call (normals' and covariances' use): the build's time is in it."""
    import lieax
    from lieax.icp import _native_kdtree

    valid = np.ones(len(target), bool)
    build = jax.jit(_native_kdtree.build)
    nearest = jax.jit(
        lambda tree, q: _native_kdtree.nearest(tree, q, np.inf, np.ones(len(q), bool))
    )
    neighbours = jax.jit(_native_kdtree.neighbours, static_argnums=2)
    tree = jax.block_until_ready(build(target, valid))

    def run(fn, *args):
        def timed():
            with lieax.threads(threads):
                return jax.tree_util.tree_map(np.asarray, fn(*args))

        return timed

    variants = {
        "build": run(build, target, valid),
        "k=1": run(nearest, tree, queries),
        "k=10": run(neighbours, target, valid, 10),
    }
    for fn in variants.values():
        fn()  # (compiled here)
    return variants


def host_tree_table(clouds, repeats):
    """Rows (cloud, library, threads, build, k=1, k=10) of the host trees, timed interleaved:
    every repeat runs every variant once, in an order rotated from repeat to repeat."""
    rows = []
    for label, (source, target, radius, truth) in clouds.items():
        target = np.ascontiguousarray(target, np.float64)
        queries = np.ascontiguousarray(aligned(source, target, radius, truth), np.float64)
        variants = {}
        for library, threads in HOST_TREES:
            for what, fn in host_tree_variants(target, queries, library, threads).items():
                variants[(library, threads, what)] = fn
        samples = {key: [] for key in variants}
        keys = list(variants)
        for r in range(repeats):
            shift = (r * 3) % len(keys)
            for key in keys[shift:] + keys[:shift]:
                start = time.perf_counter()
                variants[key]()
                samples[key].append(time.perf_counter() - start)
        medians = {key: float(np.median(v)) for key, v in samples.items()}
        fastest = {
            what: min(t for (_, _, w), t in medians.items() if w == what)
            for what in ("build", "k=1", "k=10")
        }
        for library, threads in dict.fromkeys((k[0], k[1]) for k in keys):
            cells = []
            for what in ("build", "k=1", "k=10"):
                t = medians[(library, threads, what)]
                cells.append(f"{format_seconds(t)} ({t / fastest[what]:.2f}×)")
            rows.append([label, library, "default" if threads is None else threads, *cells])
    return rows


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    _environment.add_data_dir(parser)
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--dtype", default="float32", choices=["float32", "float64"])
    parser.add_argument("--quick", action="store_true")
    parser.add_argument("--libraries", action="store_true", help="only the host trees' table")
    args = parser.parse_args()
    rounds, skip_brute_above = (2, 10_000) if args.quick else (args.rounds, 10**9)
    clouds = load_clouds(args.data_dir)
    if args.libraries:
        print_host_trees(args.data_dir, clouds, 5 if args.quick else 15)
        return
    print(f"# Nearest-neighbour backends\n\n{machine_description()}, {os.cpu_count()} CPUs, "
          f"{args.dtype}; {time.strftime('%Y-%m-%d %H:%M')}\n")  # fmt: skip
    rows, sizes = [], []
    for label, (source, target, radius, truth) in clouds.items():
        cloud_rows, within = measure(
            label, source, target, radius, truth, rounds, jnp.dtype(args.dtype), skip_brute_above
        )
        rows += cloud_rows
        sizes.append([label, f"{len(source)}/{len(target)}", f"{radius:g} m", f"{within:.1%}"])
    print(markdown_table(["cloud", "points (source/target)", "radius", "within radius"], sizes))
    print()
    headers = ["cloud", "backend", "index build", "match", "warm-started match", "exact"]
    print(markdown_table(headers, rows))
    print("\n## Host k-d trees, bare (numpy in and out)\n")
    headers = ["cloud"] + [
        f"{what} {dtype}"
        for dtype in ("f64", "f32")
        for what in ("cKDTree build", "query", "query 2 workers", "pykdtree build", "query")
    ]
    print(markdown_table(headers, [host_libraries(label, *c) for label, c in clouds.items()]))
    print_host_trees(args.data_dir, clouds, 5 if args.quick else 15)


def print_host_trees(data_dir, clouds, repeats):
    scans = np.load(os.path.join(data_dir, "clouds", "lidar_scans_0_1_2", "scans.npz"))
    clouds = {**clouds, "LiDAR raw 25k": (scans["scan1"], scans["scan0"], 1.0, None)}
    sizes = ", ".join(f"{label} {len(c[0])}/{len(c[1])}" for label, c in clouds.items())
    print(f"\n## k-d trees for lieax: cKDTree, pykdtree, small_gicp, native\n\n{os.cpu_count()} "
          f"CPUs, float64, {repeats} interleaved repeats, median (× the fastest of the three); "
          f"points (queries/target): {sizes}; {time.strftime('%Y-%m-%d %H:%M')}, load "
          f"{os.getloadavg()[0]:.1f}\n")  # fmt: skip
    headers = ["cloud", "library", "threads", "build", "query k=1", "query k=10 (self)"]
    print(markdown_table(headers, host_tree_table(clouds, repeats)))


if __name__ == "__main__":
    main()
