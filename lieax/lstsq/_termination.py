r"""`Termination`: when lieax's Levenberg-Marquardt and Gauss-Newton stop, one options object for
both doors (`lieax.lstsq.least_squares` and `lieax.factorgraph.FactorGraph.solve`, and so
`lieax.graph.optimize`), with presets that reproduce the stopping rules of GTSAM, Ceres and
MINPACK."""

import dataclasses
import operator

import jax
import numpy as np

_COUNTINGS = ("trials", "outer")
_TOLERANCES = (
    "function_tolerance",
    "absolute_function_tolerance",
    "gradient_tolerance",
    "parameter_tolerance",
)


@dataclasses.dataclass(frozen=True)
class Termination:
    r"""When a least-squares solve stops: the iteration limit, what an iteration counts, and the
    tolerances of the convergence tests. A pytree: the tolerances are leaves (they may be traced,
    and a new value reuses the compiled solve), `max_iterations` and `counting` are static (they
    shape the compiled loop).

    With $c$ the cost before an iteration, $\Delta c$ its change, $g = J^\top W r$ the gradient,
    $\delta$ the step and $x$ the point, the tests are:

    | field | test (`CONVERGED` when) | GTSAM | Ceres | MINPACK `lmder` |
    |---|---|---|---|---|
    | `function_tolerance` | $\lvert\Delta c\rvert \le \text{tol}\cdot c$ | `relativeErrorTol` | `function_tolerance` | `ftol` |
    | `absolute_function_tolerance` | $\lvert\Delta c\rvert \le \text{tol}$ | `absoluteErrorTol` | — | — |
    | `gradient_tolerance` | $\max_j \lvert g_j\rvert / (\lVert J_{:,j}\rVert\,\lVert r\rVert) \le \text{tol}$ | — | `gradient_tolerance` | `gtol` |
    | `parameter_tolerance` | $\lVert D\delta\rVert \le \text{tol}\,(\lVert D x\rVert + \text{tol})$ | — | `parameter_tolerance` | `xtol` |
    | `max_iterations` | `MAX_ITERATIONS` after that many iterations | `maxIterations` | `max_num_iterations` | `maxfev` |

    Sources: GTSAM 4.3, `NonlinearOptimizerParams` and `checkConvergence` (`NonlinearOptimizer.cpp`:
    `absoluteDecrease <= absoluteErrorTreshold || relativeDecrease <= relativeErrorTreshold`);
    Ceres 2, `Solver::Options` (`trust_region_minimizer.cc`: `|cost_change| <= function_tolerance
    * cost`, `max|x - Plus(x, -g)| <= gradient_tolerance`, `|step| <= parameter_tolerance *
    (|x| + parameter_tolerance)`); MINPACK's `lmder` (Moré, Garbow and Hillstrom, 1980: info 1
    `abs(actred) <= ftol and prered <= ftol`, info 2 `delta <= xtol*xnorm`, info 4
    `gnorm <= gtol`, the cosine of the table).

    `counting` says what an iteration is: `"trials"`, every trial point, rejected steps
    included (Ceres' iterations, successful and unsuccessful; MINPACK's function evaluations);
    `"outer"`, an outer iteration of GTSAM's `LevenbergMarquardtOptimizer`: one linearization,
    ended by a taken step, or without one when the cost change of a rejected step is below
    `function_tolerance` $\cdot\,c$ or the damping is exhausted (rejected steps are its inner
    loop).

    Each door runs the tests of its peer and refuses, with a `ValueError` naming the field, a
    setting it cannot honour:

    - `least_squares` (dense, MINPACK-style): `counting="trials"`; `function_tolerance` on a
      kept step's change and on a rejected step's predicted decrease (MINPACK's two halves),
      `absolute_function_tolerance` on a kept step's change, both strict ($<$: a tolerance of 0
      turns the test off); `gradient_tolerance` as MINPACK's cosine (not Ceres' projected
      gradient); `parameter_tolerance` as MINPACK's `xtol` in the solver's scaled variables
      $D$ (`AbstractSolver.scale`; $D = I$: Ceres' test). Its docstring details them.
    - `FactorGraph.solve` (block-sparse, GTSAM's `checkConvergence`): `counting="outer"`;
      `function_tolerance` and `absolute_function_tolerance` ($\le$, the absolute one raised to
      the rounding error of the start's cost); no gradient or step test
      (`gradient_tolerance` and `parameter_tolerance` must be 0).

    Presets (`changes`: fields to set otherwise):

    | preset | `max_iterations` | `counting` | function | absolute | gradient | parameter |
    |---|---|---|---|---|---|---|
    | `Termination()` (`least_squares`' default) | 100 | `"trials"` | dtype's | 0 | dtype's | dtype's |
    | `.gtsam()` (`FactorGraph.solve`'s default) | 100 | `"outer"` | $10^{-5}$ | $10^{-5}$ | 0 | 0 |
    | `.ceres()` | 50 | `"trials"` | $10^{-6}$ | 0 | $10^{-10}$ | $10^{-8}$ |
    | `.minpack()` (SciPy's `method="lm"`) | 100 | `"trials"` | $10^{-8}$ | 0 | $10^{-8}$ | $10^{-8}$ |

    "dtype's": `None`, which `least_squares` reads as $10^{-10}$ in float64 and $10^{-6}$ in
    float32. MINPACK's `maxfev` is $100(n + 1)$ evaluations for $n$ unknowns: pass
    `max_iterations` to match it.

    **Arguments:**

    - `max_iterations`: the most iterations (a non-negative int, static).
    - `function_tolerance`, `absolute_function_tolerance`, `gradient_tolerance`,
      `parameter_tolerance`: the tolerances of the table (non-negative; `None`: the door's
      default, `least_squares` only).
    - `counting`: `"trials"` or `"outer"` (static).
    """

    max_iterations: int = 100
    function_tolerance: float | jax.Array | None = None
    absolute_function_tolerance: float | jax.Array = 0.0
    gradient_tolerance: float | jax.Array | None = None
    parameter_tolerance: float | jax.Array | None = None
    counting: str = "trials"

    @classmethod
    def gtsam(cls, **changes) -> "Termination":
        """GTSAM 4.3's `NonlinearOptimizerParams` defaults: 100 outer iterations,
        `relativeErrorTol` and `absoluteErrorTol` $10^{-5}$, no gradient or step test."""
        preset = dict(
            max_iterations=100, function_tolerance=1e-5, absolute_function_tolerance=1e-5,
            gradient_tolerance=0.0, parameter_tolerance=0.0, counting="outer",
        )  # fmt: skip
        return cls(**{**preset, **changes})

    @classmethod
    def ceres(cls, **changes) -> "Termination":
        r"""Ceres 2's `Solver::Options` defaults: 50 iterations (rejected ones included),
        `function_tolerance` $10^{-6}$, `gradient_tolerance` $10^{-10}$, `parameter_tolerance`
        $10^{-8}$."""
        preset = dict(
            max_iterations=50, function_tolerance=1e-6, absolute_function_tolerance=0.0,
            gradient_tolerance=1e-10, parameter_tolerance=1e-8, counting="trials",
        )  # fmt: skip
        return cls(**{**preset, **changes})

    @classmethod
    def minpack(cls, **changes) -> "Termination":
        """MINPACK's `lmder` with SciPy's defaults (`least_squares(method="lm")`): `ftol`,
        `xtol` and `gtol` $10^{-8}$, 100 evaluations."""
        preset = dict(
            max_iterations=100, function_tolerance=1e-8, absolute_function_tolerance=0.0,
            gradient_tolerance=1e-8, parameter_tolerance=1e-8, counting="trials",
        )  # fmt: skip
        return cls(**{**preset, **changes})

    def __post_init__(self):
        try:
            count = operator.index(self.max_iterations)
        except TypeError:
            count = -1
        if count < 0:
            raise ValueError(
                f"Termination: max_iterations must be a non-negative int, got "
                f"{self.max_iterations!r}."
            )
        object.__setattr__(self, "max_iterations", count)  # a NumPy integer as a Python int
        if self.counting not in _COUNTINGS:
            raise ValueError(
                f"Termination: counting must be one of {_COUNTINGS}, got {self.counting!r}."
            )
        for name in _TOLERANCES:
            value = _concrete(getattr(self, name))
            if value is not None and not value >= 0:
                raise ValueError(
                    f"Termination: {name} must be non-negative (0 turns the test off), got "
                    f"{getattr(self, name)!r}."
                )

    def require(self, door: str, counting: str, zero=(), given=()):
        """Refuse (`ValueError`, naming the field) what `door` cannot honour: a `counting` other
        than its own, a tolerance of `zero` that is not 0 (a test it does not run), one of
        `given` left `None` (the door has no default for it)."""
        if self.counting != counting:
            raise ValueError(
                f"{door} counts iterations as counting={counting!r}, got Termination.counting="
                f"{self.counting!r} (see lieax.lstsq.Termination)."
            )
        for name in zero:
            value = getattr(self, name)
            if value is None or _concrete(value) != 0:
                raise ValueError(
                    f"{door} has no such test: Termination.{name} must be 0, got {value!r}."
                )
        for name in given:
            if getattr(self, name) is None:
                raise ValueError(f"{door} needs a value of Termination.{name}, got None.")


def _concrete(value):
    """`value` as a Python float when it can be checked now, else `None` (`None` itself, a
    traced value, an array of several entries, a placeholder of a pytree transformation)."""
    if isinstance(value, (float, int)) and not isinstance(value, bool):
        return float(value)
    if isinstance(value, (np.ndarray, np.number)) or (
        isinstance(value, jax.Array) and not isinstance(value, jax.core.Tracer)
    ):
        return float(np.asarray(value)) if np.ndim(value) == 0 else None
    return None


jax.tree_util.register_dataclass(
    Termination, data_fields=list(_TOLERANCES), meta_fields=["max_iterations", "counting"]
)
