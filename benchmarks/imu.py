r"""IMU preintegration and an IMU + position-fix smoother (`lieax.imu`, `lieax.factorgraph`)
against GTSAM 4.3 (`PreintegratedImuMeasurements.integrateMeasurement` called from Python, and
`LevenbergMarquardtOptimizer` on the same factors), on the generated drive of
`examples/inertial_navigation.py` (200 Hz IMU, 1 Hz fixes, one keyframe per fix).

Table 1: preintegrating all intervals (`jit(vmap(preintegrate))`, the logarithmic-depth
`preintegrate_associative`, GTSAM's loop), and the largest relative differences: lieax
sequential vs GTSAM, associative vs sequential. Table 2: the smoother, solved from the same
start by lieax (warm: structure cached, compiled) and GTSAM (default parameters), iterations and
final costs ($\tfrac12\sum\|r\|^2_\Sigma$, GTSAM's `graph.error`). Table 3: lieax's first call,
graph construction and the first solve less a warm one, in wall and CPU seconds, split into XLA
compilation (JAX's `backend_compile_duration` events) and the rest. Table 4: a stream of
intervals of 8–12 samples (`--stream 500` of them, counts drawn at random), preintegrated by
`preintegrate_intervals` (padded with masks to one bucket: one compilation) and as before it,
one `jit(vmap(preintegrate))` call per distinct count (one compilation per count): compilations,
their XLA seconds, the first call and the warm call. One pinned core, one thread each (as
`benchmarks/pgo.py`); medians over interleaved rounds in one process. Both lieax and GTSAM use
GTSAM 4.3's default IMU factor error (`Logmap`).

    python benchmarks/imu.py [--keyframes 1001] [--rounds 3] [--stream 500] [--stream-only]
"""

import argparse
import importlib.util
import os
import pathlib
import sys

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import _environment

_environment.one_core()

import time

import jax
import jax.numpy as jnp
import numpy as np
from _timing import (
    format_ratio,
    format_seconds,
    machine_description,
    markdown_table,
    time_interleaved,
)

import lieax.imu as imu
from lieax.lstsq import Termination

GTSAM_100 = Termination.gtsam(max_iterations=100)

jax.config.update("jax_enable_x64", True)

ROOT = pathlib.Path(__file__).resolve().parents[1]


def load_example():
    path = ROOT / "examples" / "inertial_navigation.py"
    spec = importlib.util.spec_from_file_location("inertial_navigation", path)
    module = importlib.util.module_from_spec(spec)
    spec.loader.exec_module(module)
    return module


def gtsam_params(example):
    import gtsam

    params = gtsam.PreintegrationParams.MakeSharedU(example.GRAVITY)
    params.setAccelerometerCovariance(example.ACCEL_DENSITY**2 * np.eye(3))
    params.setGyroscopeCovariance(example.GYRO_DENSITY**2 * np.eye(3))
    params.setIntegrationCovariance(1e-8 * np.eye(3))
    return params  # GTSAM's default ImuFactorErrorMode, Logmap: lieax's default


def gtsam_preintegrate(params, data):
    import gtsam

    pims = []
    dt = data["dt"]
    for gyro, accel in zip(data["gyro"], data["accel"]):
        pim = gtsam.PreintegratedImuMeasurements(params, gtsam.imuBias.ConstantBias())
        for k in range(len(gyro)):
            pim.integrateMeasurement(accel[k], gyro[k], dt)
        pims.append(pim)
    return pims


def gtsam_problem(example, data, pims):
    """The same factors and start as `example.build_graph`, in GTSAM."""
    import gtsam
    from gtsam.symbol_shorthand import B, V, X

    n = len(data["fixes"])
    rotations, positions, velocities, biases = example.initial_guess(data["fixes"])
    graph, initial = gtsam.NonlinearFactorGraph(), gtsam.Values()
    fix_noise = gtsam.noiseModel.Isotropic.Sigma(3, example.FIX_SIGMA)
    walk = np.repeat([example.ACCEL_BIAS_WALK, example.GYRO_BIAS_WALK], 3)
    for k in range(n):
        initial.insert(X(k), gtsam.Pose3(gtsam.Rot3(rotations[k]), positions[k]))
        initial.insert(V(k), velocities[k])
        initial.insert(B(k), gtsam.imuBias.ConstantBias(biases[k, :3], biases[k, 3:]))
        graph.add(gtsam.GPSFactor(X(k), data["fixes"][k], fix_noise))
    for k, pim in enumerate(pims):
        graph.add(gtsam.ImuFactor(X(k), V(k), X(k + 1), V(k + 1), B(k), pim))
        noise = gtsam.noiseModel.Diagonal.Sigmas(walk * np.sqrt(pim.deltaTij()))
        graph.add(
            gtsam.BetweenFactorConstantBias(B(k), B(k + 1), gtsam.imuBias.ConstantBias(), noise)
        )
    graph.add(
        gtsam.PriorFactorVector(V(0), velocities[0], gtsam.noiseModel.Isotropic.Sigma(3, 1.0))
    )
    bias_noise = gtsam.noiseModel.Diagonal.Sigmas(np.repeat([0.1, 0.01], 3))
    graph.add(gtsam.PriorFactorConstantBias(B(0), gtsam.imuBias.ConstantBias(), bias_noise))
    return graph, initial


def run_gtsam(graph, initial):
    import gtsam

    optimizer = gtsam.LevenbergMarquardtOptimizer(graph, initial, gtsam.LevenbergMarquardtParams())
    result = optimizer.optimize()
    return graph.error(result), optimizer.iterations()


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--keyframes", type=int, default=1001)
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--stream", type=int, default=500, help="intervals of Table 4")
    parser.add_argument("--stream-only", action="store_true", help="Table 4 alone")
    args = parser.parse_args(argv)
    example = load_example()
    if args.stream_only:
        print(machine_description())
        return stream_table(example, args.stream, args.rounds)
    data = example.simulate(args.keyframes, np.random.default_rng(0))
    params = example.params()
    gyro, accel = jnp.asarray(data["gyro"]), jnp.asarray(data["accel"])
    intervals, samples = data["gyro"].shape[:2]

    dt = jnp.full((intervals, samples), data["dt"])
    batched = {  # params, bias shared; the keyword samples mapped over the intervals
        name: jax.jit(jax.vmap(fn, in_axes=(None, None)))
        for name, fn in (
            ("sequential", imu.preintegrate),
            ("associative", imu.preintegrate_associative),
        )
    }
    zero = jnp.zeros(6)
    results = {
        name: fn(params, zero, accel=accel, gyro=gyro, dt=dt) for name, fn in batched.items()
    }
    g_params = gtsam_params(example)
    pims = gtsam_preintegrate(g_params, data)

    def vector(p):
        return np.concatenate([p.theta, p.delta_p, p.delta_v], axis=-1)

    def relative(a, b):
        return float(np.max(np.abs(a - b) / np.max(np.abs(b), axis=-1, keepdims=True)))

    reference = np.array([p.preintegrated() for p in pims])
    sequential, associative = results["sequential"], results["associative"]
    cov_reference = np.array([p.preintMeasCov() for p in pims])
    variants = {
        name: (lambda fn=fn: fn(params, zero, accel=accel, gyro=gyro, dt=dt).theta)
        for name, fn in batched.items()
    }
    variants["gtsam"] = lambda: jnp.asarray(gtsam_preintegrate(g_params, data)[-1].deltaTij())
    timings = time_interleaved(variants, args.rounds, warmup=0, min_sample_s=0.05)
    gtsam_loop = timings["gtsam"].median
    print(machine_description())
    print(f"\n{intervals} intervals x {samples} samples\n")
    flat = lambda x: np.asarray(x).reshape(len(x), -1)  # noqa: E731
    print(markdown_table(
        ["preintegration", "time", "vs GTSAM loop", "max rel. diff (θ,Δp,Δv)", "max rel. diff cov"],
        [
            ["lieax `preintegrate` (scan)", format_seconds(timings["sequential"].median),
             format_ratio(gtsam_loop, timings["sequential"].median),
             f"{relative(vector(sequential), reference):.1e} vs GTSAM",
             f"{relative(flat(sequential.covariance), flat(cov_reference)):.1e} vs GTSAM"],
            ["lieax `preintegrate_associative`", format_seconds(timings["associative"].median),
             format_ratio(gtsam_loop, timings["associative"].median),
             f"{relative(vector(associative), vector(sequential)):.1e} vs scan",
             f"{relative(flat(associative.covariance), flat(sequential.covariance)):.1e} vs scan"],
            ["GTSAM `integrateMeasurement` loop", format_seconds(gtsam_loop), "1.00×", "", ""],
        ],
    ))  # fmt: skip

    with FirstCall() as construction:
        graph, _ = example.build_graph(data, sequential, params)
    with FirstCall() as first_solve:
        ours = jax.block_until_ready(graph.solve(termination=GTSAM_100))
    with FirstCall() as warm_solve:
        jax.block_until_ready(graph.solve(termination=GTSAM_100))
    g_graph, g_initial = gtsam_problem(example, data, pims)
    initial_gtsam = g_graph.error(g_initial)
    gtsam_cost, gtsam_iterations = run_gtsam(g_graph, g_initial)
    solve_timings = time_interleaved(
        {"lieax": lambda: graph.solve(termination=GTSAM_100).cost,
         "gtsam": lambda: jnp.asarray(run_gtsam(g_graph, g_initial)[0])},
        args.rounds, warmup=0, min_sample_s=0.0,
    )  # fmt: skip
    print(f"\n{args.keyframes} keyframes, {intervals} IMU factors, {args.keyframes} fixes\n")
    print(markdown_table(
        ["smoother", "time", "iterations", "initial cost", "final cost", "rel. to GTSAM"],
        [
            ["lieax `FactorGraph.solve`", format_seconds(solve_timings["lieax"].median),
             int(ours.iterations), f"{float(ours.cost_history[0]):.6g}", f"{float(ours.cost):.10g}",
             f"{(float(ours.cost) - gtsam_cost) / gtsam_cost:.1e}"],
            ["GTSAM LM", format_seconds(solve_timings["gtsam"].median), gtsam_iterations,
             f"{initial_gtsam:.6g}", f"{gtsam_cost:.10g}", ""],
        ],
    ))  # fmt: skip
    linearize, linear_solve = solve_parts(graph)
    parts = time_interleaved(
        {"linearize": linearize, "linear solve": linear_solve}, args.rounds, min_sample_s=0.05
    )
    print(
        f"\nlieax / GTSAM solve time: "
        f"{format_ratio(solve_timings['lieax'].median, solve_timings['gtsam'].median)}; "
        f"lieax per solve: {int(ours.linear_solves)} linear solves of "
        f"{format_seconds(parts['linear solve'].median)} (host Cholesky), "
        f"{int(ours.iterations) + 1} linearizations of {format_seconds(parts['linearize'].median)}"
    )
    print(
        f"\nfirst call (warm solve {format_seconds(warm_solve.wall)} subtracted from the first)\n"
    )
    print(markdown_table(
        ["first call", "wall", "CPU (this process)", "XLA compile", "rest", "largest compilations"],
        [row.row(name, minus) for name, row, minus in (
            ("graph construction (`build_graph`)", construction, None),
            ("first `solve` (analysis, trace, compile)", first_solve, warm_solve),
        )],
    ))  # fmt: skip
    stream_table(example, args.stream, args.rounds)


def stream_intervals(example, count, seed=1):
    """`count` intervals of the example's drive with 8–12 samples each (drawn at random): the
    first samples of each of its intervals, `(accel, gyro)` lists and `dt`."""
    data = example.simulate(count + 1, np.random.default_rng(seed))
    counts = np.random.default_rng(seed).integers(8, 13, size=count)
    accel = [a[:n] for a, n in zip(data["accel"], counts)]
    gyro = [g[:n] for g, n in zip(data["gyro"], counts)]
    return accel, gyro, data["dt"], counts


def stream_table(example, count, rounds):
    """Table 4: `preintegrate_intervals` (masked, bucketed: one program) against one
    `jit(vmap(preintegrate))` call per distinct sample count (one program per count, as before
    masks), each with a fresh compilation cache (`jax.clear_caches`)."""
    params = example.params()
    accel, gyro, dt, counts = stream_intervals(example, count)
    groups = {n: np.flatnonzero(counts == n) for n in np.unique(counts)}

    def per_count(batched):
        out = []
        for n, index in groups.items():
            samples = dict(
                accel=np.stack([accel[k] for k in index]),
                gyro=np.stack([gyro[k] for k in index]),
                dt=np.full((len(index), n), dt),
            )
            out.append(batched(params, None, **samples).theta)
        return out

    def bucketed():
        return imu.preintegrate_intervals(params, accel=accel, gyro=gyro, dt=dt).theta

    per_count_batched = jax.jit(jax.vmap(imu.preintegrate, in_axes=(None, None)))
    variants = {
        "`preintegrate_intervals` (masks, one bucket)": bucketed,
        "one `jit(vmap(preintegrate))` per count": lambda: per_count(per_count_batched),
    }
    rows = []
    for name, call in variants.items():
        jax.clear_caches()
        with FirstCall() as first:
            jax.block_until_ready(call())
        rows.append([name, first])
    timings = time_interleaved(variants, rounds, warmup=1, min_sample_s=0.05)
    print(
        f"\n{count} intervals of {counts.min()}–{counts.max()} samples "
        f"({len(groups)} distinct counts), float64\n"
    )
    print(markdown_table(
        ["preintegration of the stream", "XLA compilations", "XLA compile", "first call (wall)",
         "first call (CPU)", "warm call"],
        [[name, len(first.compiles), format_seconds(first.compile), format_seconds(first.wall),
          format_seconds(first.cpu), format_seconds(timings[name].median)]
         for name, first in rows],
    ))  # fmt: skip


_COMPILES = []  # (function name, seconds) of every XLA compilation in this process, in order


def _record(name, seconds, fun_name="?", **_):
    if name == "/jax/core/compile/backend_compile_duration":  # these events never nest
        _COMPILES.append((fun_name, seconds))


jax.monitoring.register_event_duration_secs_listener(_record)


class FirstCall:
    """A timed block: wall and CPU seconds (this process's, so other processes' load does not
    count), and the XLA compilations in it (JAX's `backend_compile_duration` events)."""

    def __enter__(self):
        self.start, self.start_cpu, self.first = (
            time.perf_counter(),
            time.process_time(),
            len(_COMPILES),
        )
        return self

    def __exit__(self, *_):
        self.wall = time.perf_counter() - self.start
        self.cpu = time.process_time() - self.start_cpu
        self.compiles = _COMPILES[self.first :]
        self.compile = sum(seconds for _, seconds in self.compiles)

    def row(self, name, minus=None):
        """A table row: wall and CPU less those of `minus` (a warm call), compile, the rest, and
        the three largest compilations by name."""
        wall = self.wall - (minus.wall if minus else 0.0)
        cpu = self.cpu - (minus.cpu if minus else 0.0)
        by_name = {}
        for fun, seconds in self.compiles:
            by_name[fun] = by_name.get(fun, 0.0) + seconds
        top = sorted(by_name, key=by_name.get, reverse=True)[:3]
        largest = ", ".join(f"{fun} {by_name[fun]:.2f} s" for fun in top)
        return [name, format_seconds(wall), format_seconds(cpu), format_seconds(self.compile),
                format_seconds(wall - self.compile), f"{len(self.compiles)}: {largest}"]  # fmt: skip


def solve_parts(graph):
    """Callables timing one linearization (residuals, Jacobians, normal equations) and one
    damped linear solve of `graph` at its start, the two halves of an LM iteration."""
    from lieax.factorgraph._assembly import linearize
    from lieax.factorgraph._linear import solve_system

    values, data = graph.initial_values, graph.data
    lin = jax.jit(lambda v, d: linearize(graph.layout, graph.factors, graph.plans, v, d))
    _, diag, off, grad = lin(values, data)
    damped = tuple(d + 1e-5 * jnp.eye(d.shape[-1]) for d in diag)
    solve = jax.jit(lambda d, o, g: solve_system(graph.layout, "cholesky", d, o, g))
    return (lambda: lin(values, data)[0]), (lambda: solve(damped, off, grad)[0])


if __name__ == "__main__":
    main()
