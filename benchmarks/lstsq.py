"""Batched SE3 point-set alignment: lieax.lstsq under `vmap` against jaxlie in a Python loop.

A batch of small problems (default 1,000 problems of 100 point pairs each, float64) is solved
with Levenberg-Marquardt four ways:

- `lieax.lstsq.least_squares` under `jax.vmap`: one compiled call for the whole batch;
- the same, one jitted call per problem in a Python loop;
- jaxlie with Jacobians built by `jax.jacfwd` through `T @ SE3.exp(δ)`, and an LM written here
  that mirrors lieax's (same first evaluation, gain ratio, Nielsen damping update, Marquardt
  scaling and tolerances): one jitted call per problem in a Python loop (the reference);
- the jaxlie solve under `jax.vmap` (so that the batching and the Jacobians can be told apart).

Every figure is the best of `--repeats` timed runs after a warm-up (compilation is reported on its
own). The ratio column is the time of a row over the time of the lieax `vmap` row. The solutions
of all four are checked against each other.

Run: `python benchmarks/lstsq.py [--problems 1000] [--points 100] [--repeats 3] [--float32]`.
"""

import argparse
import os
import platform
import time

import jax
import jax.numpy as jnp
import numpy as np


def parse_args():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--problems", type=int, default=1000)
    parser.add_argument("--points", type=int, default=100)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument(
        "--loop-problems",
        type=int,
        default=None,
        help="problems timed in the Python loops (scaled to --problems); default all",
    )
    parser.add_argument("--float32", action="store_true")
    return parser.parse_args()


ARGS = parse_args()
jax.config.update("jax_enable_x64", not ARGS.float32)

import jaxlie  # noqa: E402

import lieax  # noqa: E402
import lieax.lstsq  # noqa: E402

DTYPE = jnp.float32 if ARGS.float32 else jnp.float64
TOLERANCE = 1e-6 if ARGS.float32 else 1e-10
MAX_ITERATIONS = 100
TERMINATION = lieax.lstsq.Termination(
    max_iterations=MAX_ITERATIONS,
    function_tolerance=TOLERANCE,
    gradient_tolerance=TOLERANCE,
    parameter_tolerance=TOLERANCE,
)


# ---- the problems ------------------------------------------------------------------------------


def make_problems(key, problems, points):
    """Random poses (rotations up to ~π, translations in [-1, 1]) and noisy point pairs."""
    k1, k2, k3, k4 = jax.random.split(key, 4)
    rotvec = jax.random.normal(k1, (problems, 3)) * 0.8
    translation = jax.random.uniform(k2, (problems, 3), minval=-1.0, maxval=1.0)
    source = jax.random.normal(k3, (problems, points, 3))
    truth = lieax.SE3.from_rotation_and_translation(lieax.SO3.exp(rotvec), translation)
    target = jax.vmap(lambda pose, cloud: pose @ cloud)(truth, source)
    target = target + 0.01 * jax.random.normal(k4, target.shape)
    return source.astype(DTYPE), target.astype(DTYPE)


# ---- lieax ---------------------------------------------------------------------------------------


def lieax_residual(pose, data):
    source, target = data
    return jax.vmap(lambda p, q: pose @ p - q)(source, target)


def lieax_solve(source, target):
    return lieax.lstsq.least_squares(
        lieax_residual,
        lieax.SE3.identity(dtype=DTYPE),
        (source, target),
        termination=TERMINATION,
        throw=False,
    )


def lieax_summary(solution):
    return solution.value.parameters(), solution.iterations, solution.status


# ---- jaxlie + jax.jacfwd, with an LM that mirrors lieax's --------------------------------------


def jaxlie_linearize(pose, source, target):
    def residual(p):
        return jax.vmap(p.apply)(source) - target

    r = residual(pose).ravel()
    jac = jax.jacfwd(lambda d: residual(pose @ jaxlie.SE3.exp(d)).ravel())(jnp.zeros(6, DTYPE))
    return 0.5 * r @ r, jac.T @ jac, jac.T @ r


@jax.jit
def jaxlie_solve(source, target):
    """Levenberg-Marquardt as in lieax.lstsq: Nielsen's damping update, Marquardt's scaling
    clipped to [1e-6, 1e32], a step kept at a gain ratio of 1e-3 (or when the cost change is below
    its rounding error), the same three tolerances."""
    eps = jnp.finfo(DTYPE).eps

    def select(condition, new, old):
        return jax.tree_util.tree_map(lambda a, b: jnp.where(condition, a, b), new, old)

    def body(state):
        pose, cost, hessian, gradient, damping, nu, trial, step, first, iteration, _ = state
        cost_t, hessian_t, gradient_t = jaxlie_linearize(trial, source, target)
        finite = jnp.isfinite(cost_t) & jnp.all(jnp.isfinite(gradient_t))
        actual = cost - cost_t
        predicted = -(gradient @ step + 0.5 * step @ hessian @ step)
        ratio = actual / jnp.where(predicted > 0, predicted, 1.0)
        ratio = jnp.where(finite & (predicted > 0), ratio, -jnp.inf)
        resolution = 16 * eps * jnp.abs(cost)
        unmeasurable = finite & (jnp.abs(predicted) <= resolution) & (actual >= -resolution)
        ratio = jnp.where(unmeasurable, 1.0, ratio)
        accept = finite & (ratio >= 1e-3)
        shrink = jnp.maximum(1 / 3, 1 - (2 * ratio - 1) ** 3)
        damping = jnp.clip(jnp.where(accept, damping * shrink, damping * nu), 1e-16, 2e32)
        nu = jnp.where(accept, 2.0, 2.0 * nu)
        accept = accept | first
        damping, nu = jnp.where(first, 1e-4, damping), jnp.where(first, 2.0, nu)
        pose, cost, hessian, gradient = select(
            accept, (trial, cost_t, hessian_t, gradient_t), (pose, cost, hessian, gradient)
        )
        iteration = jnp.where(first, iteration, iteration + 1)

        gradient_norm = jnp.max(jnp.abs(gradient))
        small_step = ~first & (
            jnp.linalg.norm(step) <= TOLERANCE * (jnp.linalg.norm(pose.wxyz_xyz) + TOLERANCE)
        )
        small_change = ~first & (jnp.abs(actual) < TOLERANCE * cost)
        converged = (small_step & finite) | (accept & (small_change | (gradient_norm <= TOLERANCE)))
        scaling = jnp.clip(jnp.diagonal(hessian), 1e-6, 1e32)
        factor = jnp.linalg.cholesky(hessian + jnp.diag(damping * scaling))
        step = jax.scipy.linalg.cho_solve((factor, True), -gradient)
        stop_nonfinite = ~finite & (first | small_step)
        done = converged | (iteration >= MAX_ITERATIONS) | (damping > 1e32) | stop_nonfinite
        trial = pose @ jaxlie.SE3.exp(step)
        return pose, cost, hessian, gradient, damping, nu, trial, step, False, iteration, done

    identity = jaxlie.SE3(jnp.array([1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0], DTYPE))
    zero, zeros6 = jnp.zeros((), DTYPE), jnp.zeros(6, DTYPE)
    initial = (
        identity,
        zero,
        jnp.zeros((6, 6), DTYPE),
        zeros6,
        zero,
        zero,
        identity,
        zeros6,
        jnp.array(True),
        jnp.array(0),
        jnp.array(False),
    )
    final = jax.lax.while_loop(lambda s: ~s[-1], body, initial)
    return final[0].wxyz_xyz, final[9], final[10]


# ---- timing ----------------------------------------------------------------------------------------


def best_time(run, repeats):
    """The best wall-clock and the best process CPU time of `repeats` runs (the CPU time is the
    steadier figure on a shared machine)."""
    walls, cpus = [], []
    for _ in range(repeats):
        wall, cpu = time.perf_counter(), time.process_time()
        jax.block_until_ready(run())
        walls.append(time.perf_counter() - wall)
        cpus.append(time.process_time() - cpu)
    return min(walls), min(cpus)


def timed_compile(run):
    start = time.perf_counter()
    jax.block_until_ready(run())
    return time.perf_counter() - start


def main():
    source, target = make_problems(jax.random.PRNGKey(0), ARGS.problems, ARGS.points)
    loop_problems = ARGS.loop_problems or ARGS.problems
    scale = ARGS.problems / loop_problems

    lieax_batched = jax.jit(jax.vmap(lambda s, t: lieax_summary(lieax_solve(s, t))))
    lieax_single = jax.jit(lambda s, t: lieax_summary(lieax_solve(s, t)))
    jaxlie_batched = jax.jit(jax.vmap(jaxlie_solve))

    def batched(solve):
        return lambda: solve(source, target)

    def looped(solve):
        return lambda: [solve(source[i], target[i]) for i in range(loop_problems)]

    methods = [
        ("lieax.lstsq, vmap over the batch", batched(lieax_batched), 1.0),
        ("lieax.lstsq, Python loop", looped(lieax_single), scale),
        ("jaxlie + jax.jacfwd, Python loop (reference)", looped(jaxlie_solve), scale),
        ("jaxlie + jax.jacfwd, vmap over the batch", batched(jaxlie_batched), 1.0),
    ]
    rows = []
    for name, run, factor in methods:
        compile_seconds = timed_compile(run)  # the loops: the first problem compiles
        wall, cpu = best_time(run, ARGS.repeats)
        rows.append((name, factor * wall, factor * cpu, compile_seconds))

    # the four agree (quaternions up to sign)
    params, iterations, status = lieax_batched(source, target)
    params_jaxlie, iterations_jaxlie, _ = jaxlie_batched(source, target)
    sign = jnp.sign(jnp.sum(params[:, :4] * params_jaxlie[:, :4], axis=1, keepdims=True))
    flip = jnp.concatenate([jnp.broadcast_to(sign, (len(sign), 4)), jnp.ones((len(sign), 3))], 1)
    difference = float(jnp.max(jnp.abs(params - params_jaxlie * flip)))
    loop_difference = float(jnp.max(jnp.abs(lieax_single(source[0], target[0])[0] - params[0])))

    base, base_cpu = rows[0][1], rows[0][2]
    device = jax.devices()[0]
    print(
        f"\nSE3 alignment, {ARGS.problems} problems x {ARGS.points} points, "
        f"{jnp.dtype(DTYPE).name}, LM tolerances {TOLERANCE:g}; {device.platform} "
        f"({device.device_kind}), {platform.machine()}, {os.cpu_count()} CPUs, "
        f"jax {jax.__version__}; best of {ARGS.repeats}"
    )
    if loop_problems != ARGS.problems:
        print(f"(Python loops timed over {loop_problems} problems, scaled to {ARGS.problems})")
    print()
    print(
        f"| {'method':<44} | {'wall':>10} | {'per problem':>11} | {'ratio':>6} | "
        f"{'CPU time':>10} | {'ratio':>6} | {'compile':>7} |"
    )
    print(f"|{'-' * 46}|{'-' * 12}|{'-' * 13}|{'-' * 8}|{'-' * 12}|{'-' * 8}|{'-' * 9}|")
    for name, wall, cpu, compile_seconds in rows:
        print(
            f"| {name:<44} | {wall * 1e3:>7.1f} ms | {wall / ARGS.problems * 1e6:>8.1f} µs | "
            f"{wall / base:>5.1f}x | {cpu * 1e3:>7.1f} ms | {cpu / base_cpu:>5.1f}x | "
            f"{compile_seconds:>5.1f} s |"
        )
    print()
    print(
        f"reference (jaxlie loop) / lieax vmap: {rows[2][1] / base:.1f}x wall, "
        f"{rows[2][2] / base_cpu:.1f}x CPU time"
    )
    counts = np.bincount(np.asarray(status), minlength=4)
    print(
        f"lieax statuses: converged {counts[0]}, max iterations {counts[1]}, diverged {counts[2]}, "
        f"non-finite {counts[3]}; iterations mean {float(jnp.mean(iterations)):.1f} "
        f"(jaxlie LM {float(jnp.mean(iterations_jaxlie)):.1f}), max {int(jnp.max(iterations))} "
        "(a vmapped batch runs the max)"
    )
    print(
        f"max |lieax - jaxlie| over the parameters: {difference:.1e}; "
        f"vmap vs single solve: {loop_difference:.1e}"
    )


if __name__ == "__main__":
    main()
