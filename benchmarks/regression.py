"""Badly scaled nonlinear regression: lieax's Levenberg-Marquardt against MINPACK on NIST StRD
problems, published and rescaled (unknowns from $10^{-9}$ to $10^3$ in one problem).

For every problem, start and variant of `tests/test_lstsq_scaling.py` (where the models, data,
certified values and the rescaling are defined) the table gives whether the solve reached NIST's
certified values to four significant digits, and its iterations: MINPACK's `lmder`
(`scipy.optimize.least_squares(method="lm", x_scale="jac")`, function evaluations), and
`lieax.lstsq.least_squares` with each `LevenbergMarquardt(scaling=...)`: `"clipped"` (lieax's
former damping, Marquardt's diagonal clipped to $[10^{-6}, 10^{32}]$), `"jacobi"` (Ceres'
`jacobi_scaling`) and `"minpack"` (the default: MINPACK's running maximum of the column norms).
All three use Nielsen's damping rule (the default); the last column is the `"minpack"` scaling
with MINPACK's trust-region radius instead (`damping_update="minpack"`: `lmder`'s radius update
and `lmpar`'s damping for the radius), which takes MINPACK's steps. All share the current
stopping rules and the Jacobi-scaled Cholesky factorization; lieax before the scaling option (the
clipped damping, an unscaled factorization and absolute gradient and step tests) solved none of
the rescaled problems. An iteration of
lieax is one evaluation of the residual and its Jacobian, rejected steps included, as MINPACK's
function evaluations. Every lieax solve runs at most 1,000 iterations in float64.

Run: `python benchmarks/regression.py` (about a minute on an idle 2-core machine).
"""

import os
import sys

import jax

jax.config.update("jax_enable_x64", True)

sys.path.insert(0, os.path.join(os.path.dirname(os.path.abspath(__file__)), "..", "tests"))

import test_lstsq_scaling as suite  # noqa: E402

import lieax.lstsq as ls  # noqa: E402

SCALINGS = ("clipped", "jacobi", "minpack")
SOLVERS = {
    **{f"lieax `{name}`": ls.LevenbergMarquardt(scaling=name) for name in SCALINGS},
    "lieax `minpack`, MINPACK's radius": ls.LevenbergMarquardt(damping_update="minpack"),
}


def cell(problem, b, iterations, status=None) -> str:
    mark = "yes" if suite.solved(problem, b) else "**no**"
    note = "" if status in (None, "CONVERGED") else f" ({status})"
    return f"{mark} {int(iterations)}{note}"


def main():
    header = ["problem", "variant", "start", "MINPACK", *SOLVERS]
    print("| " + " | ".join(header) + " |")
    print("|" + "---|" * len(header))
    totals = {name: 0 for name in ("MINPACK", *SOLVERS)}
    for problem in suite.PROBLEMS:
        results = {name: suite.lieax_results(problem, solver) for name, solver in SOLVERS.items()}
        minpack = suite.minpack_results(problem)
        for index, (variant, start, _) in enumerate(suite.cases(problem)):
            b, nfev, _ = minpack[index]
            row = [problem.name, variant, str(start), cell(problem, b, nfev)]
            totals["MINPACK"] += suite.solved(problem, b)
            for name in SOLVERS:
                b, iterations, status = results[name][index]
                row.append(cell(problem, b, iterations, status))
                totals[name] += suite.solved(problem, b)
            print("| " + " | ".join(row) + " |")
    cases = sum(len(suite.cases(problem)) for problem in suite.PROBLEMS)
    print(
        f"| **solved** | | | {totals['MINPACK']}/{cases} | "
        + " | ".join(f"{totals[name]}/{cases}" for name in SOLVERS)
        + " |"
    )


if __name__ == "__main__":
    main()
