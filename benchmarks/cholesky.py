"""The multifrontal Cholesky's numeric phase alone: the native custom call (`csrc/cholesky.cc`)
against the NumPy plan in its host callback, on the normal equations of the g2o sets' pose
graphs at their initial poses (damped by 1e-3 on the diagonal, as an LM step would be).

Both read the same `CholeskyPlan` analysis and run inside `jit` (one factorization and both
substitutions per call); medians of interleaved rounds in one process, one thread (BLAS, XLA),
the process pinned to one CPU as `benchmarks/pgo.py` is.

    python benchmarks/cholesky.py --data ../shared/data [--rounds 15] [--sets intel,sphere2500]
"""

import argparse
import os
import sys

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import _environment

_environment.one_core()

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp
from _timing import (
    format_ratio,
    format_seconds,
    machine_description,
    markdown_table,
    time_interleaved,
)
from pgo import SETS

from lieax import graph as lg
from lieax.factorgraph import _multifrontal, _native_cholesky
from lieax.factorgraph._linear import to_padded
from lieax.graph import _optimize


def system_of(path):
    """The padded normal equations of the g2o file's pose graph at its poses, and their plan."""
    graph = lg.read_g2o(path)
    factor_graph = _optimize._factor_graph(graph, True)
    layout = factor_graph.layout
    _, diag, off, grad = factor_graph.linearize(factor_graph.initial_values)
    diag, off, rhs = to_padded(layout, diag, off, grad)
    diag = diag + 1e-3 * jnp.eye(diag.shape[-1])
    return layout.plan(), (diag, off, rhs)


def solvers(plan, system):
    """The two numeric phases of `plan` on `system`, jitted, as zero-argument callables."""
    result = jax.ShapeDtypeStruct(system[2].shape, system[2].dtype)
    native = jax.jit(lambda *s: _native_cholesky.solve(plan.key, *s))
    host = jax.jit(
        lambda *s: _multifrontal.host_call(
            lambda *a: _multifrontal._host_solve(plan, *a), result, *s
        )
    )
    return {"native": lambda: native(*system), "numpy": lambda: host(*system)}


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    _environment.add_data_dir(parser)
    parser.add_argument("--rounds", type=int, default=15)
    parser.add_argument("--sets", default=",".join(SETS))
    args = parser.parse_args(argv)
    if not _native_cholesky.available():
        sys.exit("benchmarks/cholesky.py needs the native library (see setup.py)")
    print(machine_description() + "; one thread (BLAS 1), pinned")
    print()
    rows = []
    for name in args.sets.split(","):
        plan, system = system_of(os.path.join(args.data_dir, "g2o", SETS[name][0]))
        variants = solvers(plan, system)
        native, host = variants["native"](), variants["numpy"]()
        difference = float(jnp.max(jnp.abs(native - host)) / jnp.max(jnp.abs(host)))
        timings = time_interleaved(variants, args.rounds, min_sample_s=0.02)
        a, b = timings["native"].median, timings["numpy"].median
        n, d = plan.pattern.num_blocks, plan.pattern.block_size
        rows.append(
            [
                name,
                f"{n * d}",
                f"{plan.stats['fronts']}",
                f"{plan.stats['flops_unpadded']:.3g}",
                format_seconds(a),
                format_seconds(b),
                format_ratio(a, b),
                f"{difference:.1e}",
            ]
        )
        print(f"  {name}: done", file=sys.stderr)
    print(
        markdown_table(
            [
                "set",
                "unknowns",
                "fronts",
                "multiply-adds",
                "native",
                "NumPy plan",
                "native / NumPy",
                "max rel. diff",
            ],
            rows,
        )  # fmt: skip
    )


if __name__ == "__main__":
    main()
