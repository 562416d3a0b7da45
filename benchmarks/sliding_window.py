"""A growing window solved step by step: `FactorGraph(..., buckets=True)` against the default
(one compiled loop per structure), in one process.

A generated 2D trajectory (SE2 poses, odometry with sigmas 0.1 m / 0.05 rad, a prior on pose 0,
a loop closure from every 10th pose to the pose 7 before it, and every pose sighting its two
nearest of 40 landmarks at 0.2 m) is solved for windows of the first N poses, N = 50..150 (every
`--step`-th), each from its perturbed truth, the way an incremental SLAM front end calls a
batch solver in a Python loop. Per step and variant (the unbucketed first, then the bucketed),
the first solve (analysis, tracing, compilation, run; the compilations counted by JAX's
`backend_compile_duration` events), then the warm solve (median of `--repeats` calls, the two
variants interleaved). The table: total time of the first solves, compilations, median warm
time per step, and the per-step warm ratio bucketed / unbucketed (median, lowest, highest).

    python benchmarks/sliding_window.py [--step 5] [--repeats 5] [--solver auto] [--json PATH]
"""

import argparse
import os
import statistics
import sys
import time

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

import jax
import jax.numpy as jnp
import numpy as np
from _results import write
from _timing import machine_description, markdown_table

from lieax import SE2
from lieax.factorgraph import Factor, FactorGraph, Var
from lieax.factorgraph._graph import GTSAM
from lieax.graph import between_error, prior_error

jax.config.update("jax_enable_x64", True)

LANDMARKS = 40


def sighting(x, landmark, z):
    return (x.inverse() @ landmark) - z


def trajectory(count, seed=0):
    """Truth poses along a loop, the landmarks, and each pose's two nearest landmarks."""
    rng = np.random.default_rng(seed)
    t = np.arange(count) * 0.08
    xi = np.c_[
        20 * np.sin(t) + np.arange(count) * 0.1,
        12 * np.sin(2 * t),
        t + 0.05 * rng.normal(size=count),
    ]
    truth = SE2.exp(jnp.asarray(xi))
    points = rng.uniform([-25, -15], [35, 15], size=(LANDMARKS, 2))
    distance = np.linalg.norm(np.asarray(truth.translation())[:, None] - points[None], axis=-1)
    nearest = np.argsort(distance, axis=1)[:, :2]
    return truth, points, nearest


def window(data, n, buckets):
    truth, points, nearest = data
    rng = np.random.default_rng(n)  # the same measurements and start for both variants
    truth = truth[:n]
    i = np.r_[np.arange(n - 1), np.arange(10, n, 10)]
    j = np.r_[np.arange(1, n), np.arange(10, n, 10) - 7]
    odometry = truth[i].between(truth[j]).rplus(jnp.asarray(0.02 * rng.normal(size=(len(i), 3))))
    pose_of = np.repeat(np.arange(n), 2)
    seen = nearest[:n].reshape(-1)
    observed = truth[pose_of].inverse() @ jnp.asarray(points[seen])
    observed = observed + 0.05 * rng.normal(size=observed.shape)
    poses = Var(truth.rplus(jnp.asarray(0.05 * rng.normal(size=(n, 3)))), name="poses")
    used, seen_index = np.unique(seen, return_inverse=True)  # the landmarks seen so far
    start = points[used] + 0.3 * rng.normal(size=(len(used), 2))
    landmarks = Var(jnp.asarray(start), name="landmarks")
    factors = [
        Factor(between_error, (poses[i], poses[j]), odometry, sigmas=[0.1, 0.1, 0.05], name="odo"),
        Factor(prior_error, (poses[np.array([0])],), truth[:1], sigmas=[0.01] * 3, name="prior"),
        Factor(sighting, (poses[pose_of], landmarks[seen_index]), observed, sigmas=[0.2, 0.2]),
    ]
    return FactorGraph(factors, [poses, landmarks], buckets=buckets)


def main():
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--step", type=int, default=5)
    parser.add_argument("--repeats", type=int, default=5)
    parser.add_argument("--solver", default="auto")
    parser.add_argument("--first", type=int, default=50)
    parser.add_argument("--last", type=int, default=150)
    parser.add_argument("--json", help="also write the tables to this file (_results format)")
    args = parser.parse_args()
    compiles = []
    jax.monitoring.register_event_duration_secs_listener(
        lambda event, duration, **_: (
            compiles.append(duration)
            if event == "/jax/core/compile/backend_compile_duration"
            else None
        )
    )
    data = trajectory(args.last)
    variants = {"unbucketed": False, "bucketed": True}
    first = {name: [] for name in variants}
    compiled = {name: 0 for name in variants}
    warm = {name: [] for name in variants}
    differences = []
    by_method = {}  # (unbucketed's linear solver, bucketed's) -> warm ratios
    for n in range(args.first, args.last + 1, args.step):
        graphs = {name: window(data, n, buckets) for name, buckets in variants.items()}
        results = {}
        for name, graph in graphs.items():
            before = len(compiles)
            start = time.perf_counter()
            results[name] = jax.block_until_ready(graph.solve(linear_solver=args.solver))
            first[name].append(time.perf_counter() - start)
            compiled[name] += len(compiles) - before
        differences.append(abs(float(results["bucketed"].cost - results["unbucketed"].cost)))
        methods = tuple(
            graph._loop(GTSAM, args.solver, "auto", 100, None, False, None)[2]
            for graph in graphs.values()
        )
        samples = {name: [] for name in variants}
        for _ in range(args.repeats):
            for name, graph in graphs.items():
                start = time.perf_counter()
                jax.block_until_ready(graph.solve(linear_solver=args.solver))
                samples[name].append(time.perf_counter() - start)
        for name in variants:
            warm[name].append(statistics.median(samples[name]))
        by_method.setdefault(methods, []).append(warm["bucketed"][-1] / warm["unbucketed"][-1])
    ratios = [b / u for b, u in zip(warm["bucketed"], warm["unbucketed"])]
    rows = [
        [
            name,
            f"{sum(first[name]):.1f} s",
            str(compiled[name]),
            f"{1e3 * statistics.median(warm[name]):.2f} ms",
            "1" if name == "unbucketed" else
            f"{statistics.median(ratios):.2f} ({min(ratios):.2f}-{max(ratios):.2f})",
        ]
        for name in variants
    ]  # fmt: skip
    steps = len(range(args.first, args.last + 1, args.step))
    title = (
        f"Growing window N = {args.first}..{args.last} step {args.step} ({steps} steps), "
        f"linear_solver={args.solver!r}"
    )
    notes = (
        f"{machine_description()}; largest |cost difference| bucketed - unbucketed "
        f"{max(differences):.1e}"
    )
    headers = ["variant", "first solves, total", "XLA compilations", "warm solve, median step",
               "warm ratio bucketed / unbucketed (median, range)"]  # fmt: skip
    print(f"{title}, {notes}\n")
    print(markdown_table(headers, rows))
    print()
    solver_rows = [
        [f"{u} / {b}", str(len(r)), f"{statistics.median(r):.2f} ({min(r):.2f}-{max(r):.2f})"]
        for (u, b), r in by_method.items()
    ]
    solver_headers = ["linear solver (unbucketed / bucketed)", "steps",
                      "warm ratio bucketed / unbucketed"]  # fmt: skip
    print(markdown_table(solver_headers, solver_rows))
    if args.json:
        tables = [
            {"title": title, "columns": headers, "rows": rows, "notes": notes},
            {"title": "Warm ratio by linear solver", "columns": solver_headers,
             "rows": solver_rows},
        ]  # fmt: skip
        raw = {"first": first, "warm": warm, "compilations": compiled}
        write(args.json, "sliding_window", tables, raw=raw)


if __name__ == "__main__":
    main()
