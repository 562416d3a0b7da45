"""Pose-graph optimization: `lieax.graph.optimize` against GTSAM's `LevenbergMarquardtOptimizer`.

Needs the `bench` extra (GTSAM 4.3) and the g2o sets of `shared/data/g2o` (`--data` or
`LIEAX_DATA_DIR`). Both run Levenberg-Marquardt with GTSAM's default parameters from the file's
poses, one thread each (BLAS, XLA and GTSAM), GTSAM with a tight prior on the first pose and
lieax holding it fixed, as the data README describes. Both stop by the same rule, so they reach
the same final cost; the table shows both costs and their relative difference.

Reported per set: warm medians over interleaved rounds (lieax and GTSAM alternate, so machine
noise falls on both alike; a sample repeats a call for at least 20 ms, so that the
sub-millisecond sets are not one noisy call per sample), iterations, final costs, the ratio
lieax / GTSAM, and lieax's first call (structure analysis and XLA compilation) separately. A
second table shows the time per iteration as the graph grows (prefixes of a set: its first k
poses and the edges among them).

    python benchmarks/pgo.py --data ../shared/data [--rounds 7] [--sets intel,sphere2500]

One thread each means one core: the process pins itself to the last CPU it may use before JAX or
GTSAM start their thread pools (set `LIEAX_BENCH_PIN=0` to leave it unpinned). Unpinned, both
libraries keep worker threads that compete for the second core in the same process (GTSAM's TBB
workers spin after each parallel region); measured unpinned on this 2-core machine the
sub-20 ms sets swung from 1.1x to 1.8x lieax / GTSAM between runs, pinned they repeat within
about 10%.
"""

import argparse
import os
import sys

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import _environment

_environment.one_core()

import time

import jax

jax.config.update("jax_enable_x64", True)

import numpy as np
from _timing import (
    format_ratio,
    format_seconds,
    machine_description,
    markdown_table,
    time_interleaved,
)

from lieax import graph as lg

SETS = {
    "tinyGrid3D": ("tinyGrid3D.g2o", True),
    "smallGrid3D": ("smallGrid3D.g2o", True),
    "intel": ("intel.g2o", False),
    "M3500": ("input_M3500_g2o.g2o", False),
    "parking-garage": ("parking-garage.g2o", True),
    "sphere2500": ("sphere2500.g2o", True),
}


_MIN_SAMPLE_S = 0.02


def gtsam_problem(path, is3d, keep=None):
    """GTSAM's graph and initial values (optionally only poses `< keep` and edges among them),
    with the README's tight prior on the first pose."""
    import gtsam

    graph, initial = gtsam.readG2o(path, is3d)
    if keep is not None:
        small = gtsam.NonlinearFactorGraph()
        for k in range(graph.size()):
            factor = graph.at(k)
            # a factor's keys (a GTSAM factor is not iterable itself)
            if factor is not None and all(key < keep for key in list(factor.keys())):
                small.add(factor)
        values = gtsam.Values()
        for key in range(keep):
            if is3d:
                values.insert(key, initial.atPose3(key))
            else:
                values.insert(key, initial.atPose2(key))
        graph, initial = small, values
    d = 6 if is3d else 3
    first = initial.atPose3(0) if is3d else initial.atPose2(0)
    prior = (gtsam.PriorFactorPose3 if is3d else gtsam.PriorFactorPose2)(
        0, first, gtsam.noiseModel.Diagonal.Variances(np.full(d, 1e-8))
    )
    graph.add(prior)
    return graph, initial


def run_gtsam(graph, initial):
    import gtsam

    optimizer = gtsam.LevenbergMarquardtOptimizer(graph, initial, gtsam.LevenbergMarquardtParams())
    result = optimizer.optimize()
    return graph.error(result), optimizer.iterations()


def prefix_graph(graph, keep):
    """The first `keep` poses of a lieax graph (file order) and the edges among them."""
    mask = (graph.between.i < keep) & (graph.between.j < keep)
    edges = graph.edges[mask]
    root = graph.between.sqrt_information[np.flatnonzero(mask)]
    measured = graph.between.measured[np.flatnonzero(mask)]
    return lg.PoseGraph.create(
        graph.poses[:keep],
        edges,
        measured,
        sqrt_information=root,
        vertex_ids=graph.vertex_ids[:keep],
    )


def benchmark_set(name, path, is3d, rounds):
    graph = lg.read_g2o(path)
    start = time.perf_counter()
    result = lg.optimize(graph)
    first_call = time.perf_counter() - start
    gt_graph, gt_initial = gtsam_problem(path, is3d)
    gt_cost, gt_iterations = run_gtsam(gt_graph, gt_initial)

    variants = {
        "lieax": lambda: lg.optimize(graph).cost,  # floats: both calls have returned
        "gtsam": lambda: run_gtsam(gt_graph, gt_initial)[0],
    }
    timings = time_interleaved(variants, rounds, warmup=1, min_sample_s=_MIN_SAMPLE_S)
    ours, theirs = timings["lieax"].median, timings["gtsam"].median
    return {
        "name": name,
        "poses": graph.num_poses,
        "edges": graph.num_edges,
        "lieax_s": ours,
        "lieax_iterations": result.iterations,
        "lieax_solves": result.linear_solves,
        "lieax_cost": result.cost,
        "gtsam_s": theirs,
        "gtsam_iterations": gt_iterations,
        "gtsam_cost": gt_cost,
        "compile_s": max(first_call - ours, 0.0),
        "first_call_s": first_call,
    }


def growth(path, is3d, sizes, rounds):
    """Time per iteration of both on prefixes of one set."""
    graph = lg.read_g2o(path)
    rows = []
    for keep in sizes:
        keep = min(keep, graph.num_poses)
        small = prefix_graph(graph, keep)
        result = lg.optimize(small)
        gt_graph, gt_initial = gtsam_problem(path, is3d, keep)
        _, gt_iterations = run_gtsam(gt_graph, gt_initial)
        timings = time_interleaved(
            {
                "lieax": lambda small=small: lg.optimize(small).cost,
                "gtsam": lambda g=gt_graph, v=gt_initial: run_gtsam(g, v)[0],
            },
            rounds,
            warmup=1,
            min_sample_s=_MIN_SAMPLE_S,
        )
        rows.append(
            (
                keep,
                small.num_edges,
                timings["lieax"].median / max(result.iterations, 1),
                timings["gtsam"].median / max(gt_iterations, 1),
                result.iterations,
                gt_iterations,
            )
        )
    return rows


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    _environment.add_data_dir(parser)
    parser.add_argument("--rounds", type=int, default=7)
    parser.add_argument("--sets", default=",".join(SETS))
    parser.add_argument(
        "--growth",
        default="sphere2500",
        help="set whose prefixes give the time-per-iteration table ('' to skip)",
    )
    args = parser.parse_args(argv)
    try:
        import gtsam  # noqa: F401
    except ImportError:
        sys.exit("benchmarks/pgo.py needs GTSAM: pip install 'lieax[bench]'")
    folder = os.path.join(args.data_dir, "g2o")
    cores = sorted(os.sched_getaffinity(0)) if hasattr(os, "sched_getaffinity") else "all"
    print(
        machine_description()
        + f"; threads: one (BLAS {os.environ['OPENBLAS_NUM_THREADS']}), process on CPUs {cores}"
    )
    print()
    rows = []
    for name in args.sets.split(","):
        file, is3d = SETS[name]
        r = benchmark_set(name, os.path.join(folder, file), is3d, args.rounds)
        rows.append(
            [
                r["name"],
                f"{r['poses']} / {r['edges']}",
                format_seconds(r["lieax_s"]),
                f"{r['lieax_iterations']} ({r['lieax_solves']})",
                f"{r['lieax_cost']:.10g}",
                format_seconds(r["gtsam_s"]),
                str(r["gtsam_iterations"]),
                f"{r['gtsam_cost']:.10g}",
                f"{(r['lieax_cost'] - r['gtsam_cost']) / r['gtsam_cost']:.1e}",
                format_ratio(r["lieax_s"], r["gtsam_s"]),
                format_seconds(r["compile_s"]),
            ]
        )
        print(f"  {name}: done", file=sys.stderr)
    print(
        markdown_table(
            [
                "set",
                "poses / edges",
                "lieax",
                "iterations (solves)",
                "lieax cost",
                "GTSAM",
                "iterations",
                "GTSAM cost",
                "cost rel. diff",
                "lieax / GTSAM",
                "lieax compile",
            ],
            rows,
        )
    )
    if args.growth:
        file, is3d = SETS[args.growth]
        path = os.path.join(folder, file)
        total = lg.read_g2o(path).num_poses
        sizes = sorted({max(total // 8, 2), total // 4, total // 2, total})
        print()
        print(f"Time per iteration as the graph grows ({args.growth}, first k poses):")
        print()
        growth_rows = [
            [k, m, format_seconds(a), format_seconds(b), format_ratio(a, b), f"{ia} / {ib}"]
            for k, m, a, b, ia, ib in growth(path, is3d, sizes, max(3, args.rounds // 2))
        ]
        print(
            markdown_table(
                [
                    "poses",
                    "edges",
                    "lieax / iteration",
                    "GTSAM / iteration",
                    "ratio",
                    "iterations lieax / GTSAM",
                ],
                growth_rows,
            )
        )


if __name__ == "__main__":
    main()
