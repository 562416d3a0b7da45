"""The general factor-graph solver (`lieax.factorgraph`) on pose graphs, against
`lieax.graph.optimize` (the pose-graph layer over it: the column measures that layer's cost, its
cached factor graph and result conversion) and GTSAM 4.3's `LevenbergMarquardtOptimizer`, and
its first-call cost as factor kinds are added.

Needs the `bench` extra (GTSAM 4.3) and the g2o sets of `shared/data/g2o` (`--data` or
`LIEAX_DATA_DIR`). Same setup as `benchmarks/pgo.py` (one pinned core, one thread each, GTSAM's
default parameters, a tight prior on the first pose in GTSAM, the first pose fixed in lieax):
warm medians over interleaved rounds in one process, iterations, final costs, and the first
call (structure analysis, tracing and XLA compilation) separately. `factorgraph` uses the
closed-form between blocks (`lieax.graph.to_factor_graph`'s default), `factorgraph (autodiff)` lets
`lieax.jacobian` differentiate the residual through the groups' `custom_jvp` rules.

The second table is the first call on a generated 2D problem of about 10k poses as factor kinds
are added (odometry; loop closures; GPS positions; a pose prior; compass headings): analysis
(`FactorGraph(...)`), the first `solve` less a warm one split into XLA compilation (JAX's
monitoring events) and the rest (tracing, lowering, host-side setup), the first call's total in
wall and in this process's CPU seconds (a loaded machine inflates the wall time), and the warm
solve.

The last table is the Schur choice (`solve(eliminate="auto")`, the default): on a generated
bundle adjustment whose points are seen by 2-3 cameras and on generated 2D landmark SLAM whose
landmarks are seen by most poses, the warm solve with `"auto"`, with the landmarks or points
forced out by the Schur complement (which warns when the model finds it costlier) and with no
elimination, the time `"auto"`'s decision took, and the model's figures for both.

    python benchmarks/factorgraph.py --data ../shared/data [--rounds 5] [--sets intel,sphere2500]
                                     [--no-schur]
"""

import argparse
import os
import sys

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import time

import _environment
import jax
import jax.numpy as jnp
import numpy as np
import pgo
from _timing import (
    format_ratio,
    format_seconds,
    machine_description,
    markdown_table,
    time_interleaved,
)

from lieax import SE2
from lieax import graph as lg
from lieax.factorgraph import Factor, FactorGraph, Var
from lieax.lstsq import Termination

jax.config.update("jax_enable_x64", True)


def benchmark_set(name, path, is3d, rounds):
    graph = lg.read_g2o(path)
    start = time.perf_counter()
    fg, _ = lg.to_factor_graph(graph)
    ours = fg.solve()
    jax.block_until_ready(ours)
    first_call = time.perf_counter() - start
    fg_auto, _ = lg.to_factor_graph(graph, closed_form=False)
    auto = fg_auto.solve()
    reference = lg.optimize(graph)
    gt_graph, gt_initial = pgo.gtsam_problem(path, is3d)
    gt_cost, gt_iterations = pgo.run_gtsam(gt_graph, gt_initial)
    variants = {
        "factorgraph": lambda: fg.solve().cost,
        "autodiff": lambda: fg_auto.solve().cost,
        "graph": lambda: jnp.asarray(lg.optimize(graph).cost),
        "gtsam": lambda: jnp.asarray(pgo.run_gtsam(gt_graph, gt_initial)[0]),
    }
    t = time_interleaved(variants, rounds, warmup=1, min_sample_s=0.02)
    return [
        name,
        f"{graph.num_poses} / {graph.num_edges}",
        format_seconds(t["factorgraph"].median),
        format_seconds(t["autodiff"].median),
        format_seconds(t["graph"].median),
        format_seconds(t["gtsam"].median),
        (
            f"{int(ours.iterations)} / {int(auto.iterations)} / {reference.iterations} / "
            f"{gt_iterations}"
        ),
        f"{float(ours.cost):.10g}",
        f"{(float(ours.cost) - reference.cost) / reference.cost:.1e}",
        f"{(float(ours.cost) - gt_cost) / gt_cost:.1e}",
        format_ratio(t["factorgraph"].median, t["graph"].median),
        format_ratio(t["factorgraph"].median, t["gtsam"].median),
        format_seconds(first_call),
    ]


def generated_problem(n, kinds, seed=0):
    """A 2D pose graph of `n` poses with the first `kinds` of: odometry, loop closures, GPS
    positions every 10th pose, a prior on the first pose, compass headings (the rotation alone)
    every 10th pose (the first pose is fixed when there are neither GPS nor prior factors)."""
    rng = np.random.default_rng(seed)
    xi = rng.normal(size=(n, 3)) * 0.2
    xi[:, 0] += np.arange(n) * 0.5
    truth = SE2.exp(jnp.asarray(xi))
    start = truth.rplus(jnp.asarray(rng.normal(size=(n, 3)) * 0.05))
    poses = Var(start, fixed=[0] if kinds < 3 else None, name="poses")

    def between(a, b, z):
        return z.between(a.between(b)).log()

    def gps(x, p):
        return x.translation() - p

    def prior(x, z):
        return z.between(x).log()

    def heading(x, z):
        return z.between(x.rotation()).log()

    i = np.arange(n - 1)
    factors = [Factor(between, (poses[i], poses[i + 1]), truth[i].between(truth[i + 1]),
                      name="odometry")]  # fmt: skip
    if kinds >= 2:
        a = rng.integers(0, n - 20, size=n // 10)
        b = a + rng.integers(5, 20, size=a.shape)
        factors.append(Factor(between, (poses[a], poses[b]), truth[a].between(truth[b]),
                              name="loops"))  # fmt: skip
    if kinds >= 3:
        k = np.arange(0, n, 10)
        factors.append(Factor(gps, (poses[k],), truth.translation()[k], name="gps"))
    if kinds >= 4:
        factors.append(Factor(prior, (poses[np.zeros(1, int)],), truth[:1], name="prior"))
    if kinds >= 5:
        k = np.arange(5, n, 10)
        factors.append(Factor(heading, (poses[k],), truth.rotation()[k], name="heading"))
    return factors, poses


class _CompileClock:
    """Seconds of XLA compilation (JAX's `backend_compile_duration` events, which never nest),
    summed since the clock was made."""

    EVENT = "/jax/core/compile/backend_compile_duration"

    def __init__(self):
        self.seconds = 0.0
        self.compiles = []  # (function name, seconds), in order
        jax.monitoring.register_event_duration_secs_listener(self._record)

    def _record(self, event, duration, fun_name="?", **kwargs):
        if event == self.EVENT:
            self.seconds += duration
            self.compiles.append((fun_name, duration))


def first_calls(n, counts):
    """One row per number of factor kinds in `counts`: factors, analysis (`FactorGraph(...)`),
    the first solve less a warm one split into XLA compilation and the rest (tracing, lowering,
    host-side setup), the first call's total in wall and CPU seconds (CPU: this process's, so
    other processes' load does not count), the warm solve, iterations; and per row the largest
    XLA compilations of the first call (name, seconds, how many)."""
    clock = _CompileClock()
    rows, largest = [], []
    for kinds in counts:
        factors, poses = generated_problem(n, kinds)
        compiled, first_compile = clock.seconds, len(clock.compiles)
        start, start_cpu = time.perf_counter(), time.process_time()
        graph = FactorGraph(factors, [poses])
        analysed = time.perf_counter()
        result = graph.solve(termination=Termination.gtsam(max_iterations=20))
        jax.block_until_ready(result)
        first, first_cpu = time.perf_counter(), time.process_time()
        compile_s = clock.seconds - compiled
        largest.append(_largest(clock.compiles[first_compile:]))
        jax.block_until_ready(graph.solve(termination=Termination.gtsam(max_iterations=20)))
        warm, warm_cpu = time.perf_counter() - first, time.process_time() - first_cpu
        rows.append(
            [
                kinds,
                sum(f.count for f in factors),
                format_seconds(analysed - start),
                format_seconds(first - analysed - warm - compile_s),
                format_seconds(compile_s),
                format_seconds(first - start - warm),
                format_seconds(first_cpu - start_cpu - warm_cpu),
                format_seconds(warm),
                int(result.iterations),
            ]
        )
    return rows, largest


def _largest(compiles, count=3):
    """The `count` function names that took the most compile time, with their seconds and
    number of compilations, and the total number of compilations."""
    seconds, calls = {}, {}
    for name, duration in compiles:
        seconds[name] = seconds.get(name, 0.0) + duration
        calls[name] = calls.get(name, 0) + 1
    top = sorted(seconds, key=seconds.get, reverse=True)[:count]
    described = ", ".join(f"{name} {seconds[name]:.2f} s ({calls[name]}x)" for name in top)
    return f"{len(compiles)} compilations; largest: {described}"


def bundle_adjustment(cameras, points, observations, rounds):
    """A synthetic BAL problem (`lieax.ba.synthetic_bal`) with each linear solver, warm medians
    in one process: Schur complement on the points with the reduced camera system solved
    densely, by the multifrontal Cholesky or by PCG, and no elimination (the padded Cholesky)."""
    from lieax import ba

    problem = ba.synthetic_bal(cameras, points, observations, seed=0).problem
    cams = Var(problem.camera_variables(jnp.float64), fixed=[0], name="cameras")
    pts = Var(jnp.asarray(problem.points), fixed=[0], name="points")
    factor = Factor(
        ba.camera_residual,
        (cams[problem.camera_indices], pts[problem.point_indices]),
        jnp.asarray(problem.observations),
        jacobian_fn=ba.camera_jacobians,
    )
    graph = FactorGraph([factor], check_gauge=False)
    variants = {
        "Schur + dense": {"eliminate": pts, "solver": "dense"},
        "Schur + cholesky": {"eliminate": pts, "solver": "cholesky"},
        "Schur + cg": {"eliminate": pts, "solver": "cg"},
        "cholesky (no Schur)": {"eliminate": None, "solver": "cholesky"},
    }
    results, first = {}, {}
    for name, options in variants.items():
        start = time.perf_counter()
        results[name] = graph.solve(**options)
        jax.block_until_ready(results[name])
        first[name] = time.perf_counter() - start
    timings = time_interleaved(
        {name: (lambda o=o: graph.solve(**o).cost) for name, o in variants.items()},
        rounds, warmup=1, min_sample_s=0.02,
    )  # fmt: skip
    return [
        [
            name,
            format_seconds(timings[name].median),
            int(results[name].iterations),
            f"{float(results[name].cost):.10g}",
            format_seconds(first[name]),
        ]
        for name in variants
    ], float(graph.cost())


def between(a, b, z):
    return z.between(a.between(b)).log()


def pose_prior(x, z):
    return z.between(x).log()


def observe(pose, point, z):
    return pose.inverse() @ point - z


def landmark_slam(poses, landmarks, seen, seed=0):
    """`(graph, landmarks)`: 2D landmark SLAM, SE2 poses on a circle chained by odometry, a prior
    on the first, each landmark seen by about `seen` of the poses (exact measurements, the start
    perturbed)."""
    rng = np.random.default_rng(seed)
    angle = np.linspace(0.0, 2 * np.pi, poses)
    truth = SE2.exp(jnp.asarray(np.stack([10 * np.cos(angle), 10 * np.sin(angle), angle], -1)))
    marks = rng.uniform(-12, 12, size=(landmarks, 2))
    pose_index, mark_index = np.nonzero(rng.random((poses, landmarks)) < seen)
    i = np.arange(poses - 1)
    seen_at = jax.vmap(lambda x, p: x.inverse() @ p)(truth[pose_index], marks[mark_index])
    x = Var(truth.rplus(jnp.asarray(rng.normal(size=(poses, 3)) * 0.05)), name="poses")
    m = Var(jnp.asarray(marks + rng.normal(size=marks.shape) * 0.1), name="landmarks")
    graph = FactorGraph(
        [
            Factor(between, (x[i], x[i + 1]), truth[i].between(truth[i + 1])),
            Factor(pose_prior, (x[0],), truth[:1]),
            Factor(observe, (x[pose_index], m[mark_index]), seen_at),
        ]
    )
    return graph, m


def schur_choice(rounds):
    """`eliminate="auto"` against forcing the elimination and against none, warm medians in one
    process: bundle adjustment (points seen by 2-3 cameras: auto eliminates them) and landmark
    SLAM (landmarks seen by most poses: auto keeps them)."""
    import warnings

    from lieax import ba

    problem = ba.synthetic_bal(20, 400, 1000, seed=0).problem
    cams = Var(problem.camera_variables(jnp.float64), fixed=[0], name="cameras")
    pts = Var(jnp.asarray(problem.points), fixed=[0], name="points")
    bundle = FactorGraph(
        [
            Factor(
                ba.camera_residual,
                (cams[problem.camera_indices], pts[problem.point_indices]),
                jnp.asarray(problem.observations),
                jacobian_fn=ba.camera_jacobians,
            )
        ],
        check_gauge=False,
    )
    cases = {
        "BA: 20 cameras, 400 points seen by 2.5": (bundle, pts),
        "SLAM: 200 poses, 10 landmarks seen by 90%": landmark_slam(200, 10, 0.9),
        "SLAM: 500 poses, 20 landmarks seen by 35%": landmark_slam(500, 20, 0.35),
    }
    rows = []
    for name, (graph, kind) in cases.items():
        variants = {"auto": {}, "eliminated": {"eliminate": kind}, "none": {"eliminate": None}}
        start = time.perf_counter()
        choice = graph._eliminated("auto", "auto")
        decision = time.perf_counter() - start
        results = {}
        with warnings.catch_warnings(record=True) as caught:
            warnings.simplefilter("always")
            for variant, options in variants.items():
                results[variant] = jax.block_until_ready(graph.solve(**options, throw=False))
        timings = time_interleaved(
            {v: (lambda o=o, g=graph: g.solve(**o, throw=False).cost) for v, o in variants.items()},
            rounds, warmup=1, min_sample_s=0.02,
        )  # fmt: skip
        eliminated = graph._elimination_cost(graph.index(kind), "auto")
        whole = graph._elimination_cost(None, "auto")
        rows.append(
            [
                name,
                "eliminate" if choice is not None else "keep",
                format_seconds(decision),
                format_seconds(timings["auto"].median),
                format_seconds(timings["eliminated"].median),
                format_seconds(timings["none"].median),
                format_ratio(timings["eliminated"].median, timings["none"].median),
                f"{eliminated.total * 1e3:.3g} / {whole.total * 1e3:.3g}",
                f"{eliminated.off_blocks} / {whole.off_blocks}",
                "yes" if caught else "no",
                " / ".join(f"{float(r.cost):.3g}" for r in results.values()),
            ]
        )
    return rows


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    _environment.add_data_dir(parser)
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--sets", default=",".join(pgo.SETS))
    parser.add_argument("--poses", type=int, default=10000)
    parser.add_argument("--kinds", default="1,2,3,4,5", help="numbers of factor kinds ('')")
    parser.add_argument("--ba", default="20,400,2400", help="cameras,points,observations ('')")
    parser.add_argument("--schur", action=argparse.BooleanOptionalAction, default=True)
    args = parser.parse_args(argv)
    try:
        import gtsam  # noqa: F401
    except ImportError:
        sys.exit("benchmarks/factorgraph.py needs GTSAM: pip install 'lieax[bench]'")
    print(machine_description())
    print()
    rows = []
    for name in [s for s in args.sets.split(",") if s]:
        file, is3d = pgo.SETS[name]
        rows.append(
            benchmark_set(name, os.path.join(args.data_dir, "g2o", file), is3d, args.rounds)
        )
        print(f"  {name}: done", file=sys.stderr)
    if rows:
        headers = [
            "set",
            "poses / edges",
            "factorgraph",
            "factorgraph (autodiff)",
            "lieax.graph",
            "GTSAM",
            "iterations fg / auto / graph / GTSAM",
            "cost",
            "vs graph",
            "vs GTSAM",
            "fg / graph",
            "fg / GTSAM",
            "fg first call",
        ]
        print(markdown_table(headers, rows))
        print()
    if args.kinds:
        print(f"First call on a generated 2D problem of {args.poses} poses (20 iterations max):")
        print()
        headers = [
            "factor kinds",
            "factors",
            "analysis",
            "trace + lower + setup",
            "XLA compile",
            "first call",
            "first call (CPU)",
            "warm solve",
            "iterations",
        ]
        counts = [int(k) for k in args.kinds.split(",")]
        rows, largest = first_calls(args.poses, counts)
        print(markdown_table(headers, rows))
        print()
        for kinds, described in zip(counts, largest):
            print(f"- {kinds} factor kinds: {described}")
        print()
    if args.ba:
        cameras, points, observations = (int(x) for x in args.ba.split(","))
        rows, initial = bundle_adjustment(cameras, points, observations, args.rounds)
        print(
            f"Bundle adjustment, synthetic ({cameras} cameras, {points} points, "
            f"{observations} observations, initial cost {initial:.6g}):"
        )
        print()
        headers = ["linear solver", "warm solve", "iterations", "final cost", "first call"]
        print(markdown_table(headers, rows))
        print()
    if args.schur:
        print("The Schur choice: eliminate='auto' against forcing the elimination and none:")
        print()
        headers = [
            "problem",
            "auto",
            "decision",
            "auto solve",
            "eliminated",
            "not eliminated",
            "eliminated / not",
            "model (ms) eliminated / not",
            "off-diagonal blocks eliminated / not",
            "warned",
            "final cost auto / eliminated / not",
        ]
        print(markdown_table(headers, schur_choice(args.rounds)))


if __name__ == "__main__":
    main()
