r"""Scale-out with `lieax.sharding`: throughput over 1, 2, 4, 8 devices.

Two workloads, each run on meshes of the first k devices (every k compiles its own program):

- **Batched ICP** (batch axis): `--pairs` point-to-plane registrations of `--points`-point
  synthetic scans (`lieax.icp.synthetic_pair`, 10° / 10 cm apart, 2 mm noise) under
  `lieax.sharding.batch_map`: each device registers its slice of the pairs, no communication. One
  more row runs the same batch as `jax.jit(jax.vmap(...))` on sharded inputs (XLA's partitioner
  splits it, but every device runs until the slowest pair of the whole batch is done: one
  all-reduce of the loop condition per iteration).
- **ICP inner solve** (residual axis): the point-to-plane pose solve of one cloud with its
  correspondences fixed, $\min_T \sum_i (n_i^\top (T s_i - d_i))^2$ over `--residuals` pairs,
  by `lieax.lstsq.least_squares` (Levenberg-Marquardt) with `lieax.sharding.shard_residuals`:
  each device evaluates its residuals and Jacobian blocks, and the cost, $J^\top J$ and
  $J^\top r$ are summed by one all-reduce per iteration.

Reported per k: the median time per call over interleaved rounds (every k takes one sample per
round, so machine noise falls on all alike), the throughput, the speedup over one device, the
efficiency per device (speedup / k), the compile time and the collectives in the compiled
program. Results are checked against one device (1e-10 in float64). For ICP, "idle in
lockstep" is the share of loop iterations spent on pairs that had already stopped (a shard loops
until its slowest pair is done): splitting the batch lowers it, a gain that is not parallelism and
that also shows on virtual devices.

On the CPU the devices are virtual (`--xla_force_host_platform_device_count`) and each runs its
program on one thread (multithreaded Eigen off), so one device is one core's worth of work: the
speedup is bounded by the physical cores that are free, not by k. On a GPU machine the real
devices are measured too (as many as there are).

    python benchmarks/scale.py [--devices 1,2,4,8] [--pairs 32] [--points 1000]
                               [--residuals 200000] [--rounds 5] [--float32]
"""

import argparse
import os
import sys

_DEVICES_FLAG = "--xla_force_host_platform_device_count"


def parse_args(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--devices", default="1,2,4,8", help="device counts, comma-separated")
    parser.add_argument("--pairs", type=int, default=32, help="ICP pairs in the batch")
    parser.add_argument("--points", type=int, default=1000, help="points per ICP scan")
    parser.add_argument("--residuals", type=int, default=200_000, help="pairs of the inner solve")
    parser.add_argument("--rounds", type=int, default=5)
    parser.add_argument("--float32", action="store_true")
    parser.add_argument(
        "--platforms", default="cpu,gpu", help="platforms to measure where present, comma-separated"
    )
    return parser.parse_args(argv)


ARGS = parse_args()
COUNTS = sorted({int(k) for k in ARGS.devices.split(",")})
for _var in ("OPENBLAS_NUM_THREADS", "OMP_NUM_THREADS", "MKL_NUM_THREADS"):
    os.environ.setdefault(_var, "1")
os.environ["XLA_FLAGS"] = " ".join(
    [
        os.environ.get("XLA_FLAGS", ""),
        f"{_DEVICES_FLAG}={max(COUNTS)}",
        "--xla_cpu_multi_thread_eigen=false intra_op_parallelism_threads=1",
    ]
).strip()

import re  # noqa: E402
import time  # noqa: E402

import jax  # noqa: E402

jax.config.update("jax_enable_x64", not ARGS.float32)

import jax.numpy as jnp  # noqa: E402
import numpy as np  # noqa: E402

import lieax  # noqa: E402
import lieax.lstsq  # noqa: E402
from lieax import icp, sharding  # noqa: E402

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from _timing import format_seconds, machine_description, markdown_table, time_interleaved  # noqa: E402

DTYPE = jnp.float32 if ARGS.float32 else jnp.float64
TOLERANCE = 1e-4 if ARGS.float32 else 1e-10
COLLECTIVES = ("all-reduce", "all-gather", "all-to-all", "collective-permute", "reduce-scatter")


def compile_and_inspect(fn, *args):
    """Compiles `fn` for `args` (the calls then reuse it): the seconds it took and a
    `"2 all-reduce"`-style summary of the collective instructions of the compiled program."""
    start = time.perf_counter()
    text = fn.lower(*args).compile().as_text()
    seconds = time.perf_counter() - start
    counts = {kind: len(re.findall(rf"\b{kind}(?:-start)?\(", text)) for kind in COLLECTIVES}
    return seconds, ", ".join(f"{n} {kind}" for kind, n in counts.items() if n) or "none"


def lockstep_idle(iterations, shards):
    """The fraction of the batched loop's iterations spent on problems that had already stopped:
    each shard runs its loop until its slowest problem is done (`iterations` per problem, in
    batch order, split into `shards` equal slices)."""
    per_shard = np.asarray(iterations).reshape(shards, -1)
    run = np.sum(np.max(per_shard, axis=1) * per_shard.shape[1])
    return 1.0 - np.sum(per_shard) / run


def max_diff(a, b):
    return max(
        float(np.max(np.abs(np.asarray(x, np.float64) - np.asarray(y, np.float64))))
        for x, y in zip(jax.tree_util.tree_leaves(a), jax.tree_util.tree_leaves(b))
    )


# ---- the workloads -----------------------------------------------------------------------------


def icp_batch():
    """Padded clouds of `--pairs` synthetic pairs (sizes vary by ±10%)."""
    rng = np.random.default_rng(0)
    sizes = rng.integers(int(0.9 * ARGS.points), ARGS.points + 1, ARGS.pairs)
    pairs = [
        icp.synthetic_pair(
            int(n),
            rotation_deg=10.0,
            translation=0.1,
            noise=0.002,
            same_samples=False,
            seed=i,
            dtype=DTYPE,
        )
        for i, n in enumerate(sizes)
    ]
    (sources, source_mask), (targets, target_mask), (normals, _) = (
        icp.pad_clouds([pair[j] for pair in pairs], size=ARGS.points) for j in range(3)
    )
    return sources, source_mask, targets, target_mask, normals


def register(source, source_mask, target, target_mask, normals):
    return icp.point_to_plane(
        source,
        target,
        target_normals=normals,
        source_mask=source_mask,
        target_mask=target_mask,
        max_correspondence_distance=0.1,
        throw=False,
    )


def plane_problem():
    """Point-to-plane pairs of one scene, correspondences known, 2 mm along-normal noise."""
    source, target, normals, _ = icp.synthetic_pair(
        ARGS.residuals, rotation_deg=10.0, translation=0.1, noise=0.0, dtype=DTYPE
    )
    rng = np.random.default_rng(1)
    target = target + jnp.asarray(0.002 * rng.normal(size=(ARGS.residuals, 1)), DTYPE) * normals
    return source, target, normals


def plane_residual(pose, data):
    source, target, normals = data
    return jnp.sum(normals * (pose @ source - target), axis=-1)


def inner_solve(residual_fn, data):
    return lieax.lstsq.least_squares(
        residual_fn, lieax.SE3.identity(dtype=DTYPE), data, throw=False
    )


# ---- measuring ---------------------------------------------------------------------------------


def measure(platform, devices):
    counts = [k for k in COUNTS if k <= len(devices)]
    if ARGS.pairs % max(counts) or ARGS.residuals % max(counts):
        sys.exit(f"--pairs and --residuals must be multiples of {max(counts)}.")
    print(f"\n## {platform}: {len(devices)} {devices[0].device_kind} device(s)\n", flush=True)

    batch = icp_batch()
    icp_variants, icp_notes = {}, {}
    for k in counts:
        mesh = sharding.batch_mesh(devices[:k])
        fn = sharding.batch_map(register, mesh)
        args = sharding.shard_batch(batch, mesh)
        icp_variants[k] = lambda fn=fn, args=args: fn(*args)
        icp_notes[k] = compile_and_inspect(fn, *args)
    k = max(counts)
    mesh = sharding.batch_mesh(devices[:k])
    lockstep = jax.jit(jax.vmap(register))
    lockstep_args = sharding.shard_batch(batch, mesh)
    icp_variants["lockstep"] = lambda: lockstep(*lockstep_args)
    icp_notes["lockstep"] = compile_and_inspect(lockstep, *lockstep_args)

    problem = plane_problem()
    solve_variants, solve_notes = {}, {}
    for k in counts:
        mesh = sharding.batch_mesh(devices[:k], axis_name="residual")
        residual_fn = sharding.shard_residuals(plane_residual, mesh)
        fn = jax.jit(lambda data, residual_fn=residual_fn: inner_solve(residual_fn, data))
        args = sharding.shard_batch(problem, mesh)
        solve_variants[k] = lambda fn=fn, args=args: fn(args)
        solve_notes[k] = compile_and_inspect(fn, args)

    icp_timings = time_interleaved(icp_variants, ARGS.rounds, warmup=1)
    solve_timings = time_interleaved(solve_variants, ARGS.rounds, warmup=1)

    # correctness against one device
    icp_results = {name: jax.block_until_ready(fn()) for name, fn in icp_variants.items()}
    one = icp_results[counts[0]]
    worst = max(max_diff(r.transform, one.transform) for r in icp_results.values())
    same = all(np.array_equal(r.iterations, one.iterations) for r in icp_results.values())
    solutions = {k: jax.block_until_ready(fn()) for k, fn in solve_variants.items()}
    worst_solve = max(max_diff(s.value, solutions[counts[0]].value) for s in solutions.values())
    iterations = int(solutions[counts[0]].iterations)
    converged = float(np.mean(np.asarray(one.status) == icp.Status.CONVERGED))

    base = icp_timings[counts[0]].median
    rows = []
    for name, timing in icp_timings.items():
        k = max(counts) if name == "lockstep" else name
        label = f"{k} (jit∘vmap)" if name == "lockstep" else str(k)
        speedup = base / timing.median
        shards = 1 if name == "lockstep" else k
        rows.append(
            [
                label,
                format_seconds(timing.median),
                f"{ARGS.pairs / timing.median:.3g}",
                f"{speedup:.2f}×",
                f"{speedup / k:.0%}",
                f"{lockstep_idle(one.iterations, shards):.0%}",
                format_seconds(icp_notes[name][0]),
                icp_notes[name][1],
            ]
        )
    print(
        f"Batched ICP: {ARGS.pairs} point-to-plane pairs of ≤{ARGS.points} points, "
        f"iterations {int(np.min(one.iterations))}–{int(np.max(one.iterations))}, "
        f"{converged:.0%} converged; every device count's transforms within {worst:.1e} of one "
        f"device's, iterations {'identical' if same else 'DIFFERENT'}.\n"
    )
    print(
        markdown_table(
            [
                "devices",
                "time / batch",
                "pairs / s",
                "speedup",
                "efficiency / device",
                "idle in lockstep",
                "compile",
                "collectives",
            ],
            rows,
        )
    )

    base = solve_timings[counts[0]].median
    rows = []
    for k, timing in solve_timings.items():
        speedup = base / timing.median
        rows.append(
            [
                str(k),
                format_seconds(timing.median),
                f"{ARGS.residuals * (iterations + 1) / timing.median:.3g}",
                f"{speedup:.2f}×",
                f"{speedup / k:.0%}",
                format_seconds(solve_notes[k][0]),
                solve_notes[k][1],
            ]
        )
    print(
        f"\nICP inner solve: point-to-plane pose of {ARGS.residuals:,} pairs, Levenberg-Marquardt, "
        f"{iterations} iterations ({iterations + 1} linearizations); every device count within "
        f"{worst_solve:.1e} of one device.\n"
    )
    print(
        markdown_table(
            [
                "devices",
                "time / solve",
                "residuals / s",
                "speedup",
                "efficiency / device",
                "compile",
                "collectives",
            ],
            rows,
        )
    )
    ok = worst < TOLERANCE and worst_solve < TOLERANCE and same
    if not ok:
        print("\nMISMATCH: sharded results differ from one device's.")
    return ok


def main():
    print(
        f"# lieax.sharding scale-out\n\n{machine_description()}; {os.cpu_count()} CPU cores, "
        f"load average {os.getloadavg()[0]:.1f}; {'float32' if ARGS.float32 else 'float64'}; "
        f"{ARGS.rounds} interleaved rounds"
    )
    ok = True
    for platform in ARGS.platforms.split(","):
        try:
            devices = jax.devices(platform)
        except RuntimeError:
            continue  # not on this machine
        ok &= measure(platform, devices)
    if "cpu" in ARGS.platforms.split(","):
        print(
            f"\nThe CPU devices are virtual: {max(COUNTS)} of them share this machine's "
            f"{os.cpu_count()} cores, one thread each. Speedup beyond the number of free cores "
            "cannot appear here; efficiency per device falls as 1/k past it by construction. What "
            "the CPU rows do show: the results equal one device's, the work is split (each device "
            "runs its slice), the batch axis needs no communication, and the residual axis needs "
            "one small all-reduce per iteration. Real scaling needs real devices (several GPUs, or "
            "several hosts: see lieax.sharding's docstring)."
        )
    sys.exit(0 if ok else 1)


if __name__ == "__main__":
    main()
