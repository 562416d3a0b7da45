r"""Retractions on a batch of SO3 / SE3 elements: `lieax.retractions` exp, cayley and first_order.

For `--count` elements (default 100,000, float64) and one tangent each, three operations are timed
per group and retraction, each one jitted call over the whole batch:

- `rplus`: $\mathcal{R}_X(\delta)$, the parameters of the moved elements;
- `rminus`: $\mathcal{R}_X^{-1}(Y)$, the local coordinates of one batch relative to another;
- `rplus+jvp`: the retraction and its derivative along one tangent direction (`jax.jvp` with
  respect to $\delta$; what a solver's unrolled differentiation pays per step).

Variants are timed interleaved (`_timing.time_interleaved`: every variant takes one sample per
round, in rotated order, so machine noise falls on all alike); the table gives the median time per
call, the quartiles, and the ratio to `exp` on the same group and operation in the same run. The
values are checked first: every retraction's inverse recovers the tangents (1e-10 in float64), and
the retractions agree with `exp` to second order in the tangent's size.

Run: `python benchmarks/retractions.py [--count 100000] [--rounds 15] [--float32]`.
"""

import argparse
import os
import sys


def parse_args(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--count", type=int, default=100_000, help="elements in the batch")
    parser.add_argument("--rounds", type=int, default=15, help="interleaved timing rounds")
    parser.add_argument("--float32", action="store_true")
    return parser.parse_args(argv)


ARGS = parse_args()

import jax

jax.config.update("jax_enable_x64", not ARGS.float32)

import jax.numpy as jnp

import lieax
from lieax import retractions

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from _timing import (
    format_ratio,
    format_seconds,
    machine_description,
    markdown_table,
    time_interleaved,
)

DTYPE = jnp.float32 if ARGS.float32 else jnp.float64
TOLERANCE = 1e-4 if ARGS.float32 else 1e-10
CASES = {  # group -> the retractions with their own rule for it (exp first: the reference)
    lieax.SO3: ("exp", "cayley"),
    lieax.SE3: ("exp", "cayley", "first_order"),
}


def batch(G, count, seed):
    """Elements (uniform rotations, translations in [-1, 1]) and tangents of size ~0.5."""
    k1, k2, k3 = jax.random.split(jax.random.PRNGKey(seed), 3)
    x = G.sample_uniform(k1, (count,), dtype=DTYPE)
    delta = 0.3 * jax.random.normal(k2, (count, G.tangent_dim), dtype=DTYPE)
    direction = jax.random.normal(k3, (count, G.tangent_dim), dtype=DTYPE)
    return x, delta, direction


def operations(retraction):
    """The jitted operations timed for one retraction."""

    @jax.jit
    def rplus(x, delta):
        return retraction.rplus(x, delta).parameters()

    @jax.jit
    def rminus(y, x):
        return retraction.rminus(y, x)

    @jax.jit
    def rplus_jvp(x, delta, direction):
        moved, tangent = jax.jvp(lambda d: retraction.rplus(x, d)._params, (delta,), (direction,))
        return moved, tangent

    return {"rplus": rplus, "rminus": rminus, "rplus+jvp": rplus_jvp}


def check(G, x, delta):
    """Inverse round trip and second-order agreement with exp (raises on failure)."""
    for name in CASES[G]:
        retraction = getattr(retractions, name)
        y = retraction.rplus(x, delta)
        error = float(jnp.max(jnp.abs(retraction.rminus(y, x) - delta)))
        assert error < TOLERANCE, f"{G.__name__} {name}: round trip error {error:.3g}"
        small = 1e-3 * delta
        gap = float(jnp.max(jnp.abs(retraction.rplus(x, small).rminus(x.rplus(small)))))
        bound = 1e-5 if ARGS.float32 else 1e-6  # second order: |δ|² ~ 1e-6, times ~0.1
        assert gap < bound, f"{G.__name__} {name}: differs from exp by {gap:.3g} at |δ| ~ 1e-3"


def main():
    print(f"# Retractions on {ARGS.count:,} elements ({jnp.dtype(DTYPE).name})")
    print(machine_description())
    print()
    rows = []
    for G, names in CASES.items():
        x, delta, direction = batch(G, ARGS.count, seed=0)
        y = x.rplus(delta)
        check(G, x, delta)
        arguments = {"rplus": (x, delta), "rminus": (y, x), "rplus+jvp": (x, delta, direction)}
        variants = {}
        for name in names:
            for operation, fn in operations(getattr(retractions, name)).items():
                args = arguments[operation]
                variants[(name, operation)] = lambda fn=fn, args=args: fn(*args)
        timings = time_interleaved(variants, ARGS.rounds)
        for operation in arguments:
            reference = timings[("exp", operation)].median
            for name in names:
                timing = timings[(name, operation)]
                rows.append(
                    [
                        f"{G.__name__} {operation}",
                        name,
                        format_seconds(timing.median),
                        f"{format_seconds(timing.low)} – {format_seconds(timing.high)}",
                        format_ratio(timing.median, reference),
                        f"{timing.median / ARGS.count * 1e9:.1f} ns",
                    ]
                )
    print(
        markdown_table(
            ["operation", "retraction", "median", "quartiles", "vs exp", "per element"], rows
        )
    )


if __name__ == "__main__":
    main()
