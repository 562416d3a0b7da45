r"""Block Jacobians of a chain of rotations, the experiment of Sommer, Pradalier and Furgale.

For rotations $C_1, \dots, C_N$ and a vector $v$, `lieax.value_and_jacobian` returns
$y = C_N \cdots C_1 v$ and, for every $C_i$, the 3×3 block $\partial y / \partial \delta_i$
of the right perturbation $C_i \oplus \delta_i = C_i\,\mathrm{Exp}(\delta_i)$. This script
checks the blocks against the closed form $-(C_N \cdots C_i)\,[w_i]_\times$ with
$w_i = C_{i-1} \cdots C_1 v$, and times both under `jit` and `vmap` over many chains
(`benchmarks/chain.py` is the full benchmark).

    python examples/chain_jacobians.py [--chains 500] [--length 10]
"""

import argparse
import statistics
import time

import jax
import jax.numpy as jnp

import lieax


def chain(rotations, v):
    r"""$C_N \cdots C_1 v$, `rotations[0]` applied first."""
    for rotation in rotations:
        v = rotation @ v
    return v


def lieax_jacobians(quaternions, v):
    """`(y, J)` with `J[i]` the block of `C_i`, from `lieax.value_and_jacobian`."""
    rotations = tuple(lieax.SO3(quaternions[i]) for i in range(quaternions.shape[0]))
    y, blocks = lieax.value_and_jacobian(chain)(rotations, v)
    return y, jnp.stack(blocks)


def closed_form_jacobians(quaternions, v):
    """`(y, J)` from the closed form, with rotation matrices."""
    rotations = lieax.SO3(quaternions).as_matrix()
    ws = [v]
    for rotation in rotations:
        ws.append(rotation @ ws[-1])
    blocks, product = [], jnp.eye(3, dtype=v.dtype)
    for i in reversed(range(len(rotations))):
        product = product @ rotations[i]
        blocks.append(-product @ lieax.SO3.hat(ws[i]))
    return ws[-1], jnp.stack(blocks[::-1])


def median_seconds(fn, *args, calls=20):
    jax.block_until_ready(fn(*args))  # compile
    times = []
    for _ in range(calls):
        start = time.perf_counter()
        jax.block_until_ready(fn(*args))
        times.append(time.perf_counter() - start)
    return statistics.median(times)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--chains", type=int, default=500)
    parser.add_argument("--length", type=int, default=10)
    args = parser.parse_args(argv)
    jax.config.update("jax_enable_x64", True)

    quaternions = lieax.SO3.sample_uniform(
        jax.random.PRNGKey(0), (args.chains, args.length), dtype=jnp.float64
    ).parameters()
    v = jax.random.normal(jax.random.PRNGKey(1), (args.chains, 3), dtype=jnp.float64)
    ours = jax.jit(jax.vmap(lieax_jacobians))
    reference = jax.jit(jax.vmap(closed_form_jacobians))

    (y, J), (y_ref, J_ref) = ours(quaternions, v), reference(quaternions, v)
    print(
        f"{args.chains} chains of {args.length} rotations: J has shape {J.shape} (chain, i, 3, 3)"
    )
    print(f"max |y - y_closed_form| = {float(jnp.max(jnp.abs(y - y_ref))):.1e}")
    print(f"max |J - J_closed_form| = {float(jnp.max(jnp.abs(J - J_ref))):.1e}")
    t_ours, t_ref = median_seconds(ours, quaternions, v), median_seconds(reference, quaternions, v)
    print(
        f"lieax.value_and_jacobian: {t_ours * 1e3:.2f} ms, closed form: {t_ref * 1e3:.2f} ms "
        f"({t_ours / t_ref:.2f}x), median of 20 calls"
    )
    return float(jnp.max(jnp.abs(J - J_ref)))


if __name__ == "__main__":
    main()
