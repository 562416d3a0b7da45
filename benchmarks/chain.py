r"""The headline benchmark: block Jacobians of rotation chains (Sommer, Pradalier, Furgale).

Reproduces the first experiment of Sommer, Pradalier and Furgale, "Automatic Differentiation on
Differentiable Manifolds as a Tool for Robotics": the value of $y = C_N \cdots C_1 v$ and its local
Jacobian with respect to every rotation $C_i$, for N = 1, 2, 5, 10, 20, under `jit` and `vmap` over
2000 chains, float64, on the CPU. With right perturbations $C_i \to C_i \mathrm{Exp}(\delta_i)$,

$$\frac{\partial y}{\partial \delta_i} = -(C_N \cdots C_i)\,[w_i]_\times,
\qquad w_i = C_{i-1} \cdots C_1 v.$$

Variants, timed in one run, interleaved, after compilation and warm-up (medians over rounds):
- lieax: `lieax.value_and_jacobian` over a tuple of `lieax.SO3(wxyz)`, with `mode="auto"` (the
  default) and explicitly `"fwd"` and `"rev"`;
- hand-written: the closed form above in plain JAX with rotation matrices (the floor);
- jaxlie with `jax.jacrev` and with `jax.jacfwd` through `X @ SO3.exp(δ)` at δ = 0, what a jaxlie
  user writes today.
Every variant takes the same wxyz quaternions and returns `(y, J)` with `J` of shape `(N, 3, 3)`.

The same table for SE3 chains acting on a point (`J_i = [P_i, -P_i [w_i]×]` with `P_i` the rotation
of `T_N ⋯ T_i`), and for the point-to-plane ICP residual `nᵀ(T s − d)` over 100,000 points against
its 1×6 closed form `[mᵀ, (s × m)ᵀ]` with `m = Rᵀ n` (lieax per correspondence under `vmap`, as the
solvers write residuals, and over the whole cloud at once).

Targets: lieax within 1.3× of the hand-written floor at every N, and at least 10× faster than the
best jaxlie variant at N = 20. This is not a test: `tests/test_chain_agreement.py` checks that these
very functions agree to 1e-10.

Run `python benchmarks/chain.py` (defaults as above; needs the `bench` extra for jaxlie), or
`python benchmarks/chain.py --chains 16 --lengths 1,2 --repeats 3 --points 1000` as a smoke test.
For single-threaded numbers, as in the paper, pin the process to one core (`taskset -c 0 python
benchmarks/chain.py`); on a shared machine, pinning also steadies the medians.
"""

import argparse
import os
import sys

import jax
import jax.numpy as jnp
import jaxlie

import lieax

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))

from _timing import (  # noqa: E402
    format_ratio,
    format_seconds,
    machine_description,
    markdown_table,
    time_interleaved,
)

DEFAULT_LENGTHS = (1, 2, 5, 10, 20)
DEFAULT_CHAINS = 2000
DEFAULT_POINTS = 100_000
DEFAULT_REPEATS = 30

# ---- inputs --------------------------------------------------------------------------------------


def random_quaternions(key, shape, dtype=jnp.float64):
    """Uniformly random unit quaternions, wxyz, shape `(*shape, 4)`."""
    q = jax.random.normal(key, (*shape, 4), dtype=dtype)
    return q / jnp.linalg.norm(q, axis=-1, keepdims=True)


def random_poses(key, shape, dtype=jnp.float64):
    """Random SE3 parameters `(w, x, y, z, tx, ty, tz)`: uniform rotations, translations uniform
    in [-1, 1]."""
    key_q, key_t = jax.random.split(key)
    t = jax.random.uniform(key_t, (*shape, 3), dtype=dtype, minval=-1.0, maxval=1.0)
    return jnp.concatenate([random_quaternions(key_q, shape, dtype), t], axis=-1)


def chain_inputs(key, group, chains, length, dtype=jnp.float64):
    """`(params, v)`: parameters of shape `(chains, length, 4 or 7)` and vectors `(chains, 3)`."""
    key_x, key_v = jax.random.split(key)
    make = {"SO3": random_quaternions, "SE3": random_poses}[group]
    return make(key_x, (chains, length), dtype), jax.random.normal(key_v, (chains, 3), dtype=dtype)


def icp_inputs(key, points, dtype=jnp.float64):
    """`(pose, source, normals, target)`: one SE3 and `points` correspondences with unit normals."""
    key_t, key_s, key_n, key_d = jax.random.split(key, 4)
    normals = jax.random.normal(key_n, (points, 3), dtype=dtype)
    normals = normals / jnp.linalg.norm(normals, axis=-1, keepdims=True)
    source = jax.random.normal(key_s, (points, 3), dtype=dtype)
    target = source + 0.05 * jax.random.normal(key_d, (points, 3), dtype=dtype)
    return random_poses(key_t, (), dtype), source, normals, target


# ---- plain-JAX helpers for the hand-written floors ---------------------------------------------


def quat_to_matrix(q):
    """$R(q)$ of a unit wxyz quaternion, written out."""
    w, x, y, z = (q[..., i] for i in range(4))
    rows = [
        [1 - 2 * (y * y + z * z), 2 * (x * y - w * z), 2 * (x * z + w * y)],
        [2 * (x * y + w * z), 1 - 2 * (x * x + z * z), 2 * (y * z - w * x)],
        [2 * (x * z - w * y), 2 * (y * z + w * x), 1 - 2 * (x * x + y * y)],
    ]
    return jnp.stack([jnp.stack(row, axis=-1) for row in rows], axis=-2)


def cross(a, b):
    a0, a1, a2 = a[..., 0], a[..., 1], a[..., 2]
    b0, b1, b2 = b[..., 0], b[..., 1], b[..., 2]
    return jnp.stack([a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0], axis=-1)


def matvec(matrix, x):
    return jnp.einsum("...ij,...j->...i", matrix, x)


def matmul(a, b):
    return jnp.einsum("...ij,...jk->...ik", a, b)


def _stack_blocks(blocks):
    """`(N, *block)` from lieax's or jax's tuple of N Jacobian blocks."""
    return jnp.stack(blocks)


# ---- SO3 chains: (quaternions (N, 4), v (3,)) -> (y (3,), J (N, 3, 3)) ------------------------


def so3_chain(rotations, v):
    r"""$C_N \cdots C_1 v$ for a sequence of `lieax.SO3` (or `jaxlie.SO3`), `C_1` first."""
    y = v
    for rotation in rotations:
        y = rotation @ y
    return y


def so3_chain_lieax(mode="auto"):
    """The lieax variant: `lieax.value_and_jacobian` over a tuple of `SO3(wxyz)`."""
    value_and_jacobian = lieax.value_and_jacobian(so3_chain, mode=mode)

    def evaluate(quaternions, v):
        rotations = tuple(lieax.SO3(quaternions[i]) for i in range(quaternions.shape[0]))
        y, blocks = value_and_jacobian(rotations, v)
        return y, _stack_blocks(blocks)

    return evaluate


def so3_chain_hand(quaternions, v):
    r"""The closed form: forward pass for $w_i$, backward pass for $P_i = C_N \cdots C_i$, and
    $J_i = -P_i [w_i]_\times$, whose rows are $w_i \times p_r$ for the rows $p_r$ of $P_i$."""
    rotations = quat_to_matrix(quaternions)
    ws = [v]
    for i in range(quaternions.shape[0] - 1):
        ws.append(matvec(rotations[i], ws[-1]))
    y = matvec(rotations[-1], ws[-1])
    blocks, product = [], None
    for i in reversed(range(quaternions.shape[0])):
        product = rotations[i] if product is None else matmul(product, rotations[i])
        blocks.append(cross(ws[i][None, :], product))
    return y, jnp.stack(blocks[::-1])


def so3_chain_jaxlie(jac):
    """jaxlie: `jac` (`jax.jacrev` or `jax.jacfwd`) of the chain through `X @ SO3.exp(δ)` at
    δ = 0."""

    def evaluate(quaternions, v):
        rotations = [jaxlie.SO3(quaternions[i]) for i in range(quaternions.shape[0])]

        def perturbed(deltas):
            y = so3_chain(
                [x @ jaxlie.SO3.exp(d) for x, d in zip(rotations, deltas, strict=True)], v
            )
            return y, y

        zeros = tuple(jnp.zeros(3, dtype=v.dtype) for _ in rotations)
        blocks, y = jac(perturbed, has_aux=True)(zeros)
        return y, _stack_blocks(blocks)

    return evaluate


# ---- SE3 chains: (poses (N, 7), p (3,)) -> (y (3,), J (N, 3, 6)) -------------------------------


def se3_chain_lieax(mode="auto"):
    """The lieax variant: `lieax.value_and_jacobian` over a tuple of `SE3(wxyz_xyz)`."""
    value_and_jacobian = lieax.value_and_jacobian(so3_chain, mode=mode)

    def evaluate(poses, p):
        transforms = tuple(lieax.SE3(poses[i]) for i in range(poses.shape[0]))
        y, blocks = value_and_jacobian(transforms, p)
        return y, _stack_blocks(blocks)

    return evaluate


def se3_chain_hand(poses, p):
    r"""The closed form: $w_{i+1} = R_i w_i + t_i$; with $P_i = R_N \cdots R_i$,
    $J_i = [P_i,\; -P_i [w_i]_\times]$ (translation block first)."""
    rotations, translations = quat_to_matrix(poses[:, :4]), poses[:, 4:]
    ws = [p]
    for i in range(poses.shape[0] - 1):
        ws.append(matvec(rotations[i], ws[-1]) + translations[i])
    y = matvec(rotations[-1], ws[-1]) + translations[-1]
    blocks, product = [], None
    for i in reversed(range(poses.shape[0])):
        product = rotations[i] if product is None else matmul(product, rotations[i])
        blocks.append(jnp.concatenate([product, cross(ws[i][None, :], product)], axis=-1))
    return y, jnp.stack(blocks[::-1])


def se3_chain_jaxlie(jac):
    """jaxlie: `jac` of the chain through `X @ SE3.exp(δ)` at δ = 0 (jaxlie's tangent is (v, ω)
    too)."""

    def evaluate(poses, p):
        transforms = [jaxlie.SE3(poses[i]) for i in range(poses.shape[0])]

        def perturbed(deltas):
            y = so3_chain(
                [x @ jaxlie.SE3.exp(d) for x, d in zip(transforms, deltas, strict=True)], p
            )
            return y, y

        zeros = tuple(jnp.zeros(6, dtype=p.dtype) for _ in transforms)
        blocks, y = jac(perturbed, has_aux=True)(zeros)
        return y, _stack_blocks(blocks)

    return evaluate


# ---- ICP residual: (pose (7,), s, n, d (M, 3)) -> (r (M,), J (M, 6)) ---------------------------


def point_to_plane(transform, source, normals, target):
    r"""$r = n^\top (T s - d)$ for every correspondence (`transform` a lieax or jaxlie SE3)."""
    return jnp.sum(normals * (transform @ source - target), axis=-1)


def icp_lieax(pose, source, normals, target):
    r"""lieax over the whole cloud: one Jacobian of the residual vector. Forward mode (6 < M
    outputs) pushes 6 tangents through every point, about 4× the work of the closed form, which
    computes $R^\top n$ once: per-correspondence reverse mode (`icp_lieax_per_point`) is the way to
    write residuals over a batch."""
    return lieax.value_and_jacobian(point_to_plane)(lieax.SE3(pose), source, normals, target)


def icp_lieax_per_point(pose, source, normals, target):
    r"""lieax per correspondence, as the solvers write residuals: the 1×6 Jacobian of one residual
    (reverse mode pulls one cotangent, $R^\top n$, like the closed form), under `vmap`."""
    one = lieax.value_and_jacobian(point_to_plane)
    return jax.vmap(one, in_axes=(None, 0, 0, 0))(lieax.SE3(pose), source, normals, target)


def icp_hand(pose, source, normals, target):
    r"""The closed form: with $m = R^\top n$, $J = [m^\top, (s \times m)^\top]$."""
    rotation, translation = quat_to_matrix(pose[:4]), pose[4:]
    residual = jnp.sum(normals * (source @ rotation.T + translation - target), axis=-1)
    m = normals @ rotation
    return residual, jnp.concatenate([m, cross(source, m)], axis=-1)


def icp_jaxlie_fwd(pose, source, normals, target):
    """jaxlie: `jax.jacfwd` over the whole cloud through `T @ SE3.exp(δ)` at δ = 0."""
    transform = jaxlie.SE3(pose)

    def perturbed(delta):
        r = point_to_plane(transform @ jaxlie.SE3.exp(delta), source, normals, target)
        return r, r

    jac, residual = jax.jacfwd(perturbed, has_aux=True)(jnp.zeros(6, dtype=pose.dtype))
    return residual, jac


def icp_jaxlie_rev_per_point(pose, source, normals, target):
    """jaxlie: `jax.jacrev` of one residual through `T @ SE3.exp(δ)`, under `vmap`."""
    transform = jaxlie.SE3(pose)

    def one(s, n, d):
        def perturbed(delta):
            r = point_to_plane(transform @ jaxlie.SE3.exp(delta), s, n, d)
            return r, r

        jac, residual = jax.jacrev(perturbed, has_aux=True)(jnp.zeros(6, dtype=pose.dtype))
        return residual, jac

    return jax.vmap(one)(source, normals, target)


# ---- the variants, by table ----------------------------------------------------------------------

HAND = "hand-written"
LIEAX = "lieax"

CHAIN_VARIANTS = {
    "SO3": {
        HAND: so3_chain_hand,
        LIEAX: so3_chain_lieax("auto"),
        "lieax fwd": so3_chain_lieax("fwd"),
        "lieax rev": so3_chain_lieax("rev"),
        "jaxlie jacrev": so3_chain_jaxlie(jax.jacrev),
        "jaxlie jacfwd": so3_chain_jaxlie(jax.jacfwd),
    },
    "SE3": {
        HAND: se3_chain_hand,
        LIEAX: se3_chain_lieax("auto"),
        "lieax fwd": se3_chain_lieax("fwd"),
        "lieax rev": se3_chain_lieax("rev"),
        "jaxlie jacrev": se3_chain_jaxlie(jax.jacrev),
        "jaxlie jacfwd": se3_chain_jaxlie(jax.jacfwd),
    },
}

ICP_VARIANTS = {
    HAND: icp_hand,
    LIEAX: icp_lieax_per_point,
    "lieax whole cloud (fwd)": icp_lieax,
    "jaxlie jacrev per point": icp_jaxlie_rev_per_point,
    "jaxlie jacfwd whole cloud": icp_jaxlie_fwd,
}


def batched(fn):
    """`fn` of one chain, jitted and vmapped over a leading axis of chains."""
    return jax.jit(jax.vmap(fn))


# ---- tables --------------------------------------------------------------------------------------


def chain_table(group, lengths, chains, repeats, key):
    """Timings of every variant for each chain length; returns `(markdown, {N: {name: Timing}})`."""
    variants = CHAIN_VARIANTS[group]
    names = list(variants)
    jaxlie_names = [name for name in names if name.startswith("jaxlie")]
    results, rows = {}, []
    for length in lengths:
        params, v = chain_inputs(jax.random.fold_in(key, length), group, chains, length)
        compiled = {name: batched(fn) for name, fn in variants.items()}
        timings = time_interleaved(
            {name: (lambda fn=fn, p=params, v=v: fn(p, v)) for name, fn in compiled.items()},
            repeats,
        )
        results[length] = timings
        floor, ours = timings[HAND].median, timings[LIEAX].median
        best_jaxlie = min(timings[name].median for name in jaxlie_names)
        rows.append(
            [str(length)]
            + [format_seconds(timings[name].median) for name in names]
            + [format_ratio(ours, floor), format_ratio(best_jaxlie, ours)]
            + [format_ratio(timings[LIEAX].best, timings[HAND].best)]
        )
    headers = ["N", *names, "lieax / hand", "best jaxlie / lieax", "lieax / hand, best rounds"]
    return markdown_table(headers, rows), results


def icp_table(points, repeats, key):
    """Timings of the ICP residual Jacobian variants; returns `(markdown, {name: Timing})`."""
    inputs = icp_inputs(key, points)
    compiled = {name: jax.jit(fn) for name, fn in ICP_VARIANTS.items()}
    timings = time_interleaved(
        {name: (lambda fn=fn: fn(*inputs)) for name, fn in compiled.items()}, repeats
    )
    floor = timings[HAND].median
    rows = [
        [name, format_seconds(t.median), format_seconds(t.best), format_ratio(t.median, floor)]
        for name, t in timings.items()
    ]
    return markdown_table(["variant", "median", "best", "/ hand"], rows), timings


def verdicts(results):
    """The two targets, checked on the SO3 table: lines of text."""
    worst = max(t[LIEAX].median / t[HAND].median for t in results.values())
    worst_best = max(t[LIEAX].best / t[HAND].best for t in results.values())
    lines = [
        f"- lieax within 1.3× of hand-written at every N: {'yes' if worst <= 1.3 else 'no'} "
        f"(worst {worst:.2f}× on medians, {worst_best:.2f}× on best rounds)"
    ]
    if 20 in results:
        t = results[20]
        best = min(x.median for name, x in t.items() if name.startswith("jaxlie"))
        speedup = best / t[LIEAX].median
        lines.append(
            f"- lieax at least 10× faster than the best jaxlie at N = 20: "
            f"{'yes' if speedup >= 10 else 'no'} ({speedup:.1f}×)"
        )
    return lines


def _lengths(text):
    try:
        lengths = tuple(int(part) for part in text.split(","))
    except ValueError:
        raise argparse.ArgumentTypeError(
            f"expected comma-separated integers, got {text!r}"
        ) from None
    if not lengths or min(lengths) < 1:
        raise argparse.ArgumentTypeError(f"chain lengths must be positive, got {text!r}")
    return lengths


def parse_args(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument(
        "--chains",
        type=int,
        default=DEFAULT_CHAINS,
        help=f"chains under vmap (default {DEFAULT_CHAINS})",
    )
    parser.add_argument(
        "--lengths",
        type=_lengths,
        default=DEFAULT_LENGTHS,
        help="comma-separated chain lengths N (default 1,2,5,10,20)",
    )
    parser.add_argument(
        "--repeats",
        type=int,
        default=DEFAULT_REPEATS,
        help=f"interleaved timing rounds (default {DEFAULT_REPEATS})",
    )
    parser.add_argument(
        "--points",
        type=int,
        default=DEFAULT_POINTS,
        help=f"ICP correspondences (default {DEFAULT_POINTS})",
    )
    parser.add_argument(
        "--tables",
        default="so3,se3,icp",
        help="which tables, comma-separated from so3, se3, icp (default all)",
    )
    parser.add_argument("--seed", type=int, default=0)
    return parser.parse_args(argv)


def main(argv=None):
    args = parse_args(argv)
    jax.config.update("jax_enable_x64", True)
    tables = {part.strip().lower() for part in args.tables.split(",")}
    unknown = tables - {"so3", "se3", "icp"}
    if unknown:
        raise SystemExit(f"unknown tables {sorted(unknown)}; choose from so3, se3, icp")
    key = jax.random.PRNGKey(args.seed)
    print("# Chain benchmark (Sommer et al.): value and local Jacobian of C_N ⋯ C_1 v\n")
    print(
        f"{machine_description()}; {args.chains} chains under vmap, float64, "
        f"medians of wall-clock time over {args.repeats} interleaved rounds, "
        f"load average {os.getloadavg()[0]:.1f} on {os.cpu_count()} CPUs.\n"
    )
    so3_results = None
    for group in ("SO3", "SE3"):
        if group.lower() not in tables:
            continue
        acted_on = "a vector" if group == "SO3" else "a point"
        print(f"## {group} chains acting on {acted_on}, time per call ({args.chains} chains)\n")
        table, results = chain_table(
            group, args.lengths, args.chains, args.repeats, jax.random.fold_in(key, len(group))
        )
        print(table + "\n")
        if group == "SO3":
            so3_results = results
    if "icp" in tables:
        print(f"## Point-to-plane ICP residual Jacobian, {args.points} points\n")
        table, _ = icp_table(args.points, args.repeats, jax.random.fold_in(key, 7))
        print(table + "\n")
    if so3_results is not None:
        print("Targets (SO3 table):")
        print("\n".join(verdicts(so3_results)))


if __name__ == "__main__":
    jax.config.update("jax_platforms", "cpu")  # the experiment is defined on the CPU
    main()
