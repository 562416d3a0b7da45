"""lieax against its peers on a busy machine: every workflow timed idle and under a background load.

A user's machine is rarely idle (a browser, a compiler, other jobs), and a library whose threads
busy-wait, or ask for every core, slows down far more there than one that stays on few threads.
This benchmark times each workflow twice, (a) as the machine is and (b) with a background load it
starts itself: one busy Python process per core (spinning, each bounded to `--load-seconds` and
stopped by the benchmark when the phase ends, on an exception and on Ctrl-C). lieax and its peer
run interleaved in one process, each with its default settings (no pinning, no thread variables:
unlike `pgo.py`, `ba.py`, `imu.py` and `icp.py`, whose builders this reuses, and which set their
processes up as scripts, `benchmarks/_environment.py`); lieax as installed, with its native library
(k-d tree, Cholesky) where it is built; the header names every variable set that would change a
library's threads or paths (`SETTINGS`). A sample is one warm call (after a quarter second of
calls of each, `warm_up`), the medians over `--rounds` are compared (more rounds for a workflow
whose calls are short, as many as fit in half a second, at most 201: `rounds_for`), and lieax's
first call (compilation) is reported separately.

The floor: a load slows every program down, by as much as the machine's scheduler decides, and
that changes from one phase to the next. Each row also times a single-threaded NumPy workload
(sorts of one array, calibrated to lieax's idle time) in the same rounds, so the table shows what
the scheduler gave one busy thread in that phase (`floor loaded / idle`) and lieax's slowdown
against it (`lieax / floor`, its loaded / idle divided by the floor's). On this 2-core machine
with two spinners the floor itself went from 1.0x to 2.0x from phase to phase (December 2026).

Workflows (the peer in brackets):
- pose graphs, `pgo.py`'s g2o sets, `lieax.graph.optimize` [GTSAM's LM];
- bundle adjustment at Ladybug-49 size (`lieax.ba.SYNTHETIC_PRESETS`), 20 iterations at most,
  `ba.lieax_solver` [Ceres' SPARSE_SCHUR with COLMAP's C++ cost, `ba.run_ceres_colmap`];
- point-to-plane ICP on the LiDAR and Kinect pairs of `neighbors.load_clouds` and the pairs of
  consecutive scans of `_scan_pairs.py` (LiDAR 0.25 m, Kinect 1 cm and 3 cm), Open3D's target
  normals for both, `icp.py`'s distances and normals, criteria 1e-6 / 30, the tree built in every
  call as Open3D's [Open3D's `registration_icp`];
- GICP on `gicp.py`'s Kinect 2 cm pair and `_scan_pairs.py`'s pairs, each library's total
  (covariances, tree, registration) [small_gicp's `align`];
- the IMU smoother of `examples/inertial_navigation.py` (`imu.py`'s problem) [GTSAM's LM].

    LIEAX_DATA_DIR=../shared/data python benchmarks/under_load.py [--quick] [--only pgo,ba,icp,
        gicp,imu] [--rounds 5] [--json PATH]

`--quick`: two pose-graph sets, 201 IMU keyframes, 3 rounds. Needs the `bench` extra.

`--processes N`: the whole measurement again in N fresh processes, and a second table of the
spread over them (lowest, median and highest of each row's loaded / idle times). A warm call under
load is not one number: with the same compiled program, some processes run it nearly as fast as
idle and others at 2-3x (point-to-plane ICP on the 0.25 m LiDAR pair: 25 or 55-65 ms against 23-29
idle; the same with XLA's pool cut to one thread; the mode holds for a process's life more often
than not). One process samples one mode; several show both.
"""

import argparse
import contextlib
import json
import os
import statistics
import subprocess
import sys
import tempfile
import time

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import _environment

try:
    import gtsam  # noqa: F401
    import open3d  # noqa: F401
    import pyceres  # noqa: F401
    import pycolmap  # noqa: F401
    import small_gicp  # noqa: F401
except ImportError as error:
    sys.exit(f"benchmarks/under_load.py needs the bench extra: {error}")

# The other benchmarks' builders, imported as libraries: their own process settings (one pinned
# core, passive OpenMP) are skipped, so every library here runs with its defaults.
with _environment.library_defaults():
    import ba
    import gicp
    import icp as icp_bench
    import imu as imu_bench
    import pgo

import _results
import _scan_pairs
import jax
import jax.numpy as jnp
import numpy as np
from _timing import format_seconds, machine_description, markdown_table

from lieax import graph as lg
from lieax import icp
from lieax.icp import _host_kdtree
from lieax.lstsq import Termination

# Variables that change a library's threads or code paths: the header names those set.
SETTINGS = (
    "LIEAX_NATIVE", "OMP_NUM_THREADS", "OMP_WAIT_POLICY", "OPENBLAS_NUM_THREADS",
    "MKL_NUM_THREADS", "XLA_FLAGS", "TBB_NUM_THREADS",
)  # fmt: skip

WORKFLOWS = ("pgo", "ba", "icp", "gicp", "imu")
ICP_SCANS = ("LiDAR", "Kinect", "LiDAR 0.25 m", "Kinect 1 cm", "Kinect 3 cm")
PGO_SETS = ("tinyGrid3D", "smallGrid3D", "intel", "M3500", "parking-garage", "sphere2500")
PGO_QUICK = ("smallGrid3D", "sphere2500")
_SPIN = "import time\nend = time.monotonic() + {seconds}\nwhile time.monotonic() < end:\n    pass\n"


# ---- the background load -------------------------------------------------------------------------


@contextlib.contextmanager
def background_load(processes, seconds):
    """`processes` busy Python processes, each spinning for at most `seconds`, stopped on exit
    (normal, exception or Ctrl-C); yields nothing. With 0 processes, does nothing."""
    spinners = []
    try:
        for _ in range(processes):
            spinners.append(subprocess.Popen([sys.executable, "-c", _SPIN.format(seconds=seconds)]))
        time.sleep(0.5)  # let them reach the scheduler
        yield
    finally:
        for spinner in spinners:
            spinner.kill()
        for spinner in spinners:
            spinner.wait()


def timed_call(fn):
    """Seconds of one call of `fn` (a JAX result is waited for); `fn` may instead return its own
    measured seconds as `("seconds", s)` (a peer that must rebuild its problem untimed)."""
    start = time.perf_counter()
    out = fn()
    elapsed = time.perf_counter() - start
    if isinstance(out, tuple) and len(out) == 2 and out[0] == "seconds":
        return out[1]
    jax.block_until_ready(out)
    return elapsed


def floor_workload(seconds):
    """A single-threaded workload of about `seconds` on an idle machine: sorts of one array of
    16,384 doubles (NumPy's sort runs on the calling thread and wakes no other), as many as take
    `seconds` (at least one)."""
    values = np.random.default_rng(0).random(16384)
    np.sort(values)
    unit = statistics.median(timed_call(lambda: np.sort(values)) for _ in range(21))
    repeats = max(1, round(seconds / unit))

    def work():
        for _ in range(repeats):
            np.sort(values)

    return work


def warm_up(fn, seconds=0.25):
    """Calls of `fn` until `seconds` have passed (at least two); returns the seconds per call. A
    compiled program's first calls run slower than its later ones (tinyGrid3D's `optimize`,
    alternating with GTSAM's, in two processes: 0.6-0.9 ms per call over its first 20 calls, 0.4
    ms from the 100th on), which a median of five single calls right after the first would report
    as its warm time."""
    start, calls = time.perf_counter(), 0
    while calls < 2 or time.perf_counter() - start < seconds:
        timed_call(fn)
        calls += 1
    return (time.perf_counter() - start) / calls


def rounds_for(seconds_per_round, rounds, budget=0.5, most=201):
    """`rounds`, or more for a short workflow: as many as fit in `budget` seconds idle (at most
    `most`). Under load a call of under a millisecond either runs within its time slice or waits
    out a spinner's (a few ms): the median of five such calls is the luck of five draws
    (tinyGrid3D under load, alternating with GTSAM: 0.9-1.2x GTSAM's time in four processes,
    3.0x and 6.5x in two; over 200 rounds 0.9-1.2x in each of eleven)."""
    return max(rounds, min(most, int(budget / seconds_per_round)))


def interleaved(variants, rounds):
    """Median seconds of each variant (name -> callable, already warm) over `rounds`, one call each
    per round in an order rotated from round to round; and the load average over the rounds."""
    names, samples = list(variants), {name: [] for name in variants}
    for r in range(rounds):
        shift = r % len(names)
        for name in names[shift:] + names[:shift]:
            samples[name].append(timed_call(variants[name]))
    return {name: statistics.median(v) for name, v in samples.items()}, os.getloadavg()[0]


# ---- workflows: (label, lieax callable, peer name, peer callable, note) --------------------------


def pose_graphs(data_dir, quick):
    for name in PGO_QUICK if quick else PGO_SETS:
        file, is3d = pgo.SETS[name]
        path = os.path.join(data_dir, "g2o", file)
        graph = lg.read_g2o(path)
        gt_graph, gt_initial = pgo.gtsam_problem(path, is3d)
        yield (
            f"pose graph {name}",
            lambda graph=graph: lg.optimize(graph).cost,
            "GTSAM",
            lambda g=gt_graph, v=gt_initial: pgo.run_gtsam(g, v)[0],
        )


def bundle_adjustment(data_dir, quick):
    iterations = 20
    _, problem = ba.load_problem("ladybug-49")
    solve = ba.lieax_solver(problem, iterations, "trivial", 1.0)

    def ceres():
        run = ba.run_ceres_colmap(problem, iterations, "trivial", 1.0)  # built untimed
        return ("seconds", run.total_s)

    yield "bundle adjustment Ladybug-49 size", lambda: solve().cost, "Ceres", ceres


def point_to_plane(data_dir, quick):
    clouds = icp_bench.scan_clouds(data_dir)
    o3d = icp_bench.o3d.pipelines.registration
    for label in ICP_SCANS:
        source, target, radius, _, normals_radius = clouds[label]
        normals = icp_bench.scan_normals(target, normals_radius)
        source_cloud = icp_bench.open3d_cloud(source)
        target_cloud = icp_bench.open3d_cloud(target, normals)
        estimation = o3d.TransformationEstimationPointToPlane()
        criteria = o3d.ICPConvergenceCriteria(1e-6, 1e-6, 30)
        s, t, n = (jnp.asarray(x) for x in (source, target, normals))

        def ours(s=s, t=t, n=n, radius=radius):
            _host_kdtree._TREES.clear()  # the tree rebuilt in every call, as Open3D's
            _host_kdtree._IDS.clear()
            result = icp.point_to_plane(s, t, target_normals=n, max_correspondence_distance=radius)
            return result.transform.parameters()

        def theirs(a=source_cloud, b=target_cloud, radius=radius, e=estimation, c=criteria):
            icp_bench.o3d.pipelines.registration.registration_icp(a, b, radius, np.eye(4), e, c)

        yield f"point-to-plane {label} {len(source)}/{len(target)}", ours, "Open3D", theirs


def generalized_icp(data_dir, quick):
    pairs = [
        (pair.label, pair.source, pair.target, pair.distance)
        for pair in _scan_pairs.scan_pairs(data_dir).values()
    ]
    kinect_source, kinect_target, _ = gicp.kinect(data_dir)
    for label, source, target, distance in [
        ("Kinect 2 cm", kinect_source, kinect_target, 0.05),
        *pairs,
    ]:
        run = gicp.lieax_total(source, target, distance, jnp.float64)
        yield (
            f"GICP {label} {len(source)}/{len(target)}",
            lambda run=run: run().transform.parameters(),
            "small_gicp",
            gicp.small_gicp_total(source, target, distance),
        )


def imu_smoother(data_dir, quick):
    keyframes = 201 if quick else 1001
    example = imu_bench.load_example()
    data = example.simulate(keyframes, np.random.default_rng(0))
    params = example.params()
    preintegrated = example.preintegrate_all(data, params)
    graph, _ = example.build_graph(data, preintegrated, params)
    pims = imu_bench.gtsam_preintegrate(imu_bench.gtsam_params(example), data)
    g_graph, g_initial = imu_bench.gtsam_problem(example, data, pims)
    yield (
        f"IMU smoother {keyframes} keyframes",
        lambda: graph.solve(termination=Termination.gtsam(max_iterations=100)).cost,
        "GTSAM",
        lambda: imu_bench.run_gtsam(g_graph, g_initial)[0],
    )


BUILDERS = {
    "pgo": pose_graphs,
    "ba": bundle_adjustment,
    "icp": point_to_plane,
    "gicp": generalized_icp,
    "imu": imu_smoother,
}


# ---- the table -----------------------------------------------------------------------------------


def measure(label, ours, peer, theirs, rounds, load_seconds):
    start = time.perf_counter()
    timed_call(ours)
    first = time.perf_counter() - start
    per_round = 2 * warm_up(ours) + warm_up(theirs)  # lieax, the peer and the floor
    rounds = rounds_for(per_round, rounds)
    variants = {"lieax": ours, peer: theirs, "floor": floor_workload(timed_call(ours))}
    idle, idle_load = interleaved(variants, rounds)
    with background_load(os.cpu_count(), load_seconds):
        timed_call(ours)  # one call to settle under the load
        timed_call(theirs)
        busy, busy_load = interleaved(variants, rounds)

    def phase(times, load):
        return {"lieax_s": times["lieax"], "peer_s": times[peer], "floor_s": times["floor"],
                "load_average": load}  # fmt: skip

    return {
        "workflow": label,
        "peer": peer,
        "rounds": rounds,
        "lieax_first_call_s": first,
        "idle": phase(idle, idle_load),
        "loaded": phase(busy, busy_load),
    }


def slowdowns(record):
    """`(lieax, peer, floor)`: each one's loaded / idle time in `record`."""
    idle, busy = record["idle"], record["loaded"]
    return tuple(busy[key] / idle[key] for key in ("lieax_s", "peer_s", "floor_s"))


def row(record):
    idle, busy = record["idle"], record["loaded"]
    idle_ratio = idle["lieax_s"] / idle["peer_s"]
    busy_ratio = busy["lieax_s"] / busy["peer_s"]
    ours, theirs, floor = slowdowns(record)
    return [
        record["workflow"],
        record["peer"],
        format_seconds(idle["lieax_s"]),
        format_seconds(idle["peer_s"]),
        f"{idle_ratio:.2f}×",
        format_seconds(busy["lieax_s"]),
        format_seconds(busy["peer_s"]),
        f"{busy_ratio:.2f}×",
        f"{ours:.2f}×",
        f"{theirs:.2f}×",
        f"{floor:.2f}×",
        f"{ours / floor:.2f}×",
        f"{busy_ratio / idle_ratio:.2f}×",
        f"{idle['load_average']:.1f} / {busy['load_average']:.1f}",
        format_seconds(record["lieax_first_call_s"]),
    ]


HEADERS = [
    "workflow", "peer", "lieax idle", "peer idle", "ratio idle", "lieax loaded", "peer loaded",
    "ratio loaded", "lieax loaded / idle", "peer loaded / idle", "floor loaded / idle",
    "lieax / floor", "ratio loaded / ratio idle",
    "load avg idle / loaded", "lieax first call",
]  # fmt: skip


def settings():
    """The `SETTINGS` variables set in this process's environment, or that none is."""
    found = [f"{name}={os.environ[name]!r}" for name in SETTINGS if name in os.environ]
    return "set: " + ", ".join(found) if found else "no thread or path variable set"


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    _environment.add_data_dir(parser)
    parser.add_argument("--quick", action="store_true")
    parser.add_argument("--only", default=",".join(WORKFLOWS), help="comma-separated workflows")
    parser.add_argument("--rounds", type=int, default=None, help="default 5 (3 with --quick)")
    parser.add_argument("--load-seconds", type=float, default=600.0,
                        help="the longest a load process lives (each phase stops its own)")  # fmt: skip
    parser.add_argument("--json", default=None, help="also write the records to this file")
    parser.add_argument("--processes", type=int, default=1,
                        help="repeat the measurement in this many fresh processes and add a table "
                        "of the spread over them")  # fmt: skip
    args = parser.parse_args(argv)
    only = [w for w in args.only.split(",") if w]
    unknown = [w for w in only if w not in BUILDERS]
    if unknown:
        parser.error(f"--only: unknown workflows {unknown}; choose from {list(WORKFLOWS)}.")
    rounds = args.rounds or (3 if args.quick else 5)
    if args.processes < 1:
        parser.error(f"--processes must be at least 1, got {args.processes}.")
    if args.processes > 1:
        return over_processes(args, argv if argv is not None else sys.argv[1:], rounds)
    print(f"# lieax and its peers, idle and under load\n\n{machine_description()}, "
          f"{os.cpu_count()} CPUs, load {os.getloadavg()[0]:.1f} at the start; background load: "
          f"{os.cpu_count()} spinning processes; at least {rounds} rounds (short calls more); "
          f"{time.strftime('%Y-%m-%d %H:%M')}; {settings()}\n", flush=True)  # fmt: skip
    records = []
    for workflow in only:
        for label, ours, peer, theirs in BUILDERS[workflow](args.data_dir, args.quick):
            records.append(measure(label, ours, peer, theirs, rounds, args.load_seconds))
            print("| " + " | ".join(str(c) for c in row(records[-1])) + " |", flush=True)
    print()
    print(markdown_table(HEADERS, [row(r) for r in records]))
    if args.json:
        title = f"Warm times idle and under load, at least {rounds} rounds" + (
            " (--quick)" if args.quick else ""
        )
        notes = (
            f"Background load: {os.cpu_count()} spinning processes, started and stopped by the "
            "benchmark; lieax and its peer interleaved in one process, default settings on both "
            f"({settings()})."
        )
        tables = [{"title": title, "columns": HEADERS, "rows": [row(r) for r in records]}]
        _results.write(args.json, "under_load", tables, notes=notes, raw=records)


# ---- the spread over fresh processes --------------------------------------------------------------


def _without_option(argv, name):
    """`argv` without the option `name` and its value (`--name V` or `--name=V`)."""
    out, skip = [], False
    for item in argv:
        if skip:
            skip = False
        elif item == name:
            skip = True
        elif not item.startswith(name + "="):
            out.append(item)
    return out


def over_processes(args, argv, rounds):
    """Run this benchmark `args.processes` times, each in a fresh process (its own compilation,
    its own threads), print each process's table and the spread of every row over them."""
    child_argv = _without_option(_without_option(argv, "--processes"), "--json")
    runs = []
    with tempfile.TemporaryDirectory() as folder:
        for index in range(args.processes):
            path = os.path.join(folder, f"run{index}.json")
            print(f"## process {index + 1} of {args.processes}", flush=True)
            subprocess.run([sys.executable, os.path.abspath(__file__), *child_argv, "--json", path],
                           check=True)  # fmt: skip
            with open(path, encoding="utf-8") as file:
                runs.append(json.load(file)["raw"])
    labels = [record["workflow"] for record in runs[0]]
    spread = [spread_row(label, [r for run in runs for r in run if r["workflow"] == label])
              for label in labels]  # fmt: skip
    print(f"\n## Spread over {args.processes} fresh processes (at least {rounds} rounds each)\n")
    print(markdown_table(SPREAD_HEADERS, spread))
    if args.json:
        notes = (
            f"Each of {args.processes} fresh processes measured every row idle and under a "
            f"background load of {os.cpu_count()} spinning processes ({settings()}); lowest / "
            "median / highest over the processes."
        )
        table = {"title": f"Loaded / idle over {args.processes} fresh processes",
                 "columns": SPREAD_HEADERS, "rows": spread}  # fmt: skip
        _results.write(args.json, "under_load", [table], notes=notes, raw=runs)


SPREAD_HEADERS = [
    "workflow", "peer", "lieax idle (median)", "lieax / peer idle: low / median / high",
    "lieax / peer loaded: low / median / high", "lieax loaded / idle: low / median / high",
    "peer loaded / idle: low / median / high", "floor loaded / idle: low / median / high",
    "lieax / floor: low / median / high", "ratio loaded / ratio idle: low / median / high",
    "processes with lieax loaded > 2× idle",
]  # fmt: skip


def spread_row(label, records):
    """The table row of workflow `label` from its records of every process."""

    def triple(values):
        return " / ".join(
            f"{v:.2f}×" for v in (min(values), statistics.median(values), max(values))
        )

    ours, theirs, floors = zip(*(slowdowns(r) for r in records))
    idle = [r["idle"]["lieax_s"] / r["idle"]["peer_s"] for r in records]
    loaded = [r["loaded"]["lieax_s"] / r["loaded"]["peer_s"] for r in records]
    return [
        label,
        records[0]["peer"],
        format_seconds(statistics.median(r["idle"]["lieax_s"] for r in records)),
        triple(idle),
        triple(loaded),
        triple(ours),
        triple(theirs),
        triple(floors),
        triple([a / b for a, b in zip(ours, floors)]),
        triple([b / a for a, b in zip(idle, loaded)]),
        f"{sum(v > 2.0 for v in ours)} of {len(records)}",
    ]


if __name__ == "__main__":
    main()
