r"""The decisions of a Levenberg-Marquardt / Gauss-Newton iteration, written once for the two loops
of the library: `least_squares` (dense normal equations, `_least_squares`, through the solvers of
`_solvers`) and the factor-graph loop (block-sparse normal equations, `lieax.factorgraph._solve`).

A loop solves the damped normal equations $(H + \mu D)\,\delta = -g$ ($H = J^\top W J$,
$g = J^\top W r$), evaluates the cost $c$ at the trial point $x \oplus \delta$, and asks this
module:

- how good the step was: the gain ratio `gain_ratio` (actual over predicted decrease);
- whether to keep it: `accepts`;
- the next damping: `nielsen` (Madsen-Nielsen-Tingleff, Ceres) or `gtsam` (GTSAM 4.3), or the
  next trust-region radius: `minpack` (MINPACK's `lmder`; the dense loop then finds the damping
  whose step fits the radius, `_normal_equations.damping_for_radius`);
- whether the solve diverged: `damping_exhausted` (Levenberg-Marquardt: no damping is left to
  try), `cost_diverged` (Gauss-Newton);
- what to report: `status`, from the loop's own stopping tests.

What stays in each loop is what differs in substance: the linear algebra (dense or block-sparse),
how a trial point is linearized, and which tests of the one `Termination` each loop runs
(MINPACK-style scaled tests for `least_squares`, GTSAM's cost-change tests for the factor graph).
Where the peers differ in a comparison ($\ge$ or $>$), the caller's options say which
(`LevenbergMarquardt.inclusive_gain_ratio`, `inclusive_max_damping`). Everything here is a
pure `jnp` function of scalars (or arrays of them, under `vmap`): it adds no kernels of its own
to a compiled loop, the loop's XLA fusions absorb it.
"""

import jax
import jax.numpy as jnp

from ._solution import Status


def gain_ratio(actual, predicted) -> jax.Array:
    r"""The gain ratio (GTSAM's "model fidelity", Ceres' "relative decrease")
    $\varrho = (c(x) - c(x \oplus \delta)) / (m(0) - m(\delta))$, `actual` over `predicted`,
    with $m(\delta) = c(x) + g^\top\delta + \tfrac12 \delta^\top H \delta$ the Gauss-Newton
    model, so $m(0) - m(\delta) = -g^\top\delta - \tfrac12\delta^\top H\delta$ (for a step
    solved with damping $\mu D$: $\tfrac12(-g^\top\delta + \mu\,\delta^\top D\delta)$; Madsen,
    Nielsen and Tingleff, "Methods for non-linear least squares problems", 2004, eq. 2.14, 3.14).

    A non-positive `predicted` divides `actual` by 1: the ratio is then meaningless, and each
    loop says what such a step means (rejected, or trusted below the cost's rounding error).
    """
    return actual / jnp.where(predicted > 0, predicted, 1.0)


def accepts(gain_ratio, min_gain_ratio, *, inclusive: bool) -> jax.Array:
    r"""Whether a step with gain ratio $\varrho$ is taken: $\varrho \ge \varrho_{\min}$
    (`inclusive`, MINPACK's `lmder`: `ratio >= p0001`, the convention of `least_squares`) or
    $\varrho > \varrho_{\min}$ (GTSAM's `modelFidelity > minModelFidelity`, Ceres'
    `relative_decrease > min_relative_decrease`, the factor graph's)."""
    return gain_ratio >= min_gain_ratio if inclusive else gain_ratio > min_gain_ratio


def nielsen(accept, gain_ratio, damping, factor) -> tuple[jax.Array, jax.Array]:
    r"""Nielsen's damping update, `(damping, factor)` after a step with gain ratio $\varrho$:
    taken, $\mu \leftarrow \mu \max(\tfrac13, 1 - (2\varrho - 1)^3)$ and $\nu \leftarrow 2$;
    rejected, $\mu \leftarrow \nu\mu$ and $\nu \leftarrow 2\nu$ (Madsen, Nielsen and Tingleff,
    "Methods for non-linear least squares problems", 2004, Sec. 3.2, eq. 3.15; Ceres'
    `LevenbergMarquardtStrategy`, which holds the radius $1/\mu$). $\nu$ starts at 2.

    Example: from $\mu = 1$, $\nu = 2$: rejected, $(2, 4)$; rejected, $(8, 8)$; taken with
    $\varrho = 1$, $(8/3, 2)$; taken with $\varrho = \tfrac12$, $(8/3, 2)$ (factor 1).
    """
    shrink = jnp.maximum(1.0 / 3.0, 1.0 - (2.0 * gain_ratio - 1.0) ** 3)
    damping = jnp.where(accept, damping * shrink, damping * factor)
    factor = jnp.where(accept, 2.0, 2.0 * factor)
    return damping, factor


def minpack(finite, gain_ratio, actual, cost, slope, step_norm, radius, damping):
    r"""MINPACK's trust-region update (`lmder`), `(radius, damping)` after a step $\delta$ with
    gain ratio $\varrho$, of scaled length $p = \|D\delta\| \le \Delta$ (`step_norm`,
    `radius`), solved with the Levenberg parameter $\mu$ (`damping`):

    - $\varrho \le \tfrac14$: $\Delta \leftarrow \tau \min(\Delta, 10 p)$ and
      $\mu \leftarrow \mu / \tau$, with $\tau = \tfrac12$ if the cost did not rise, else the
      minimizer of the quadratic through $c(x)$, the slope $g^\top\delta$ and $c(x \oplus
      \delta)$ along the step, $\tau = \tfrac12\, g^\top\delta / (g^\top\delta + c(x) -
      c(x \oplus \delta))$; $\tau = \tfrac1{10}$ if that is smaller, or the residual grew tenfold
      ($c(x \oplus \delta) \ge 100\,c(x)$, or is not finite);
    - $\varrho \ge \tfrac34$, or $\tfrac14 < \varrho < \tfrac34$ after a Gauss-Newton step
      ($\mu = 0$): $\Delta \leftarrow 2p$, $\mu \leftarrow \mu / 2$;
    - otherwise unchanged.

    The step of the next iteration is the one with $\|D\delta\| \le \Delta$
    (`_normal_equations.damping_for_radius`, MINPACK's `lmpar`, starting from this $\mu$).
    Moré, "The Levenberg-Marquardt algorithm: implementation and theory", 1978, Sec. 4;
    MINPACK's `lmder` (Garbow, Hillstrom and Moré, 1980), where `actred` $= \text{actual}/c$,
    `dirder` $= g^\top\delta / (2c)$ and `temp` $= \tau$. `actual` is
    $c(x) - c(x \oplus \delta)$, `cost` $c(x)$, `slope` $g^\top\delta$.

    Example: a step of length $p = 1$ with $\varrho = 0.9$ sets $\Delta = 2$ whatever
    $\Delta$ was; one with $\varrho = 0.1$ that still decreased the cost sets
    $\Delta = \min(\Delta, 10) / 2$, $\mu = 2\mu$.
    """
    shrink = jnp.where(
        actual >= 0, 0.5, 0.5 * slope / jnp.where(slope + actual < 0, slope + actual, -1.0)
    )
    blown_up = ~finite | (actual <= -99.0 * cost)
    shrink = jnp.where(blown_up | ~(shrink >= 0.1), 0.1, shrink)
    poor = ~finite | ~(gain_ratio > 0.25)
    grow = ~poor & ((damping == 0) | (gain_ratio >= 0.75))
    radius = jnp.where(
        poor,
        shrink * jnp.minimum(radius, 10.0 * step_norm),
        jnp.where(grow, 2.0 * step_norm, radius),
    )
    damping = jnp.where(poor, damping / shrink, jnp.where(grow, 0.5 * damping, damping))
    return radius, damping


def gtsam(accept, damping, factor) -> jax.Array:
    r"""GTSAM 4.3's damping update (`LevenbergMarquardtOptimizer`, `decreaseLambda` and
    `increaseLambda` with `useFixedLambdaFactor`): $\lambda \leftarrow \lambda / f$ after a
    taken step, $\lambda \leftarrow \lambda f$ after a rejected one ($f$ = `lambdaFactor`,
    10 by default)."""
    return jnp.where(accept, damping / factor, damping * factor)


def damping_exhausted(damping, max_damping, *, inclusive: bool) -> jax.Array:
    r"""Whether the damping has grown past its bound without a step being taken, the
    Levenberg-Marquardt divergence test: $\mu \ge \mu_{\max}$ (`inclusive`, GTSAM's
    `lambda >= lambdaUpperBound`, the factor graph's) or $\mu > \mu_{\max}$ (Ceres' trust radius
    $1/\mu$ below `min_trust_region_radius`, `least_squares`')."""
    return damping >= max_damping if inclusive else damping > max_damping


def cost_diverged(cost, initial_cost, divergence_factor) -> jax.Array:
    r"""The Gauss-Newton divergence test (it has no damping to exhaust): the cost exceeds
    `divergence_factor` times the initial cost."""
    return cost > divergence_factor * initial_cost


def status(nonfinite, converged, diverged, out_of_iterations) -> jax.Array:
    """The `Status` code (`int32`) of an iteration from the loop's tests, in this order of
    precedence: `NONFINITE`, `CONVERGED`, `DIVERGED`, `MAX_ITERATIONS`, else `RUNNING`."""
    return jnp.where(
        nonfinite,
        Status.NONFINITE,
        jnp.where(
            converged,
            Status.CONVERGED,
            jnp.where(
                diverged,
                Status.DIVERGED,
                jnp.where(out_of_iterations, Status.MAX_ITERATIONS, Status.RUNNING),
            ),
        ),
    ).astype(jnp.int32)
