r"""Gauss-Newton and Levenberg-Marquardt: how a step is computed from the normal equations and
whether it is kept.

A solver is a pytree (its numeric settings are leaves, so they may be traced; settings that choose
a method, such as `LevenbergMarquardt.scaling`, are static) whose methods the loop of
`least_squares` calls:

- `init(dimension, dtype)`: its state (damping, scaling and the like) at the first iterate;
- `step(state, hessian, gradient)`: the step $\delta$ in flattened tangent coordinates and the
  state it was computed with;
- `update(state, gain_ratio, finite, actual, cost)`: whether the trial point $x \oplus \delta$
  is kept, and the next state, from the gain ratio $\varrho$ (actual over predicted decrease of
  the cost), whether the trial point was finite, the actual decrease
  $c(x) - c(x \oplus \delta)$ and the cost $c(x)$;
- `diverged(state, cost, initial_cost)`: whether to stop with `Status.DIVERGED`;
- `damping(state)`: the damping, for the iteration table;
- `scale(state)`: the scaling $d$ of the variables (all ones for unscaled solvers): the stopping
  rules measure the gradient as $D^{-1} g$ and the step as $D\delta$, $D = \mathrm{diag}(d)$,
  so that they do not depend on the units of the unknowns.

`rejects_steps` says whether a rejected (non-finite) trial point is an ordinary event
(Levenberg-Marquardt shrinks the step and tries again) or the end of the solve (Gauss-Newton).

The decisions themselves (acceptance, the damping rules, the divergence tests) are those of
`_trust_region`, which the factor-graph loop shares; what is this module's own is the dense
linear algebra (the scaling of the variables, the damped system and its solve, the damping
that fits a step into a trust region).
"""

import dataclasses
from typing import ClassVar

import jax
import jax.numpy as jnp

from . import _trust_region as trust_region
from ._normal_equations import damping_for_radius, solve_spd

_SCALINGS = ("minpack", "jacobi", "clipped", "identity")
_DAMPING_UPDATES = ("nielsen", "minpack", "gtsam")


class AbstractSolver:
    """Base of the dense normal-equation solvers; see the module docstring for the interface."""

    rejects_steps: ClassVar[bool]

    def __init_subclass__(cls, **kwargs):
        super().__init_subclass__(**kwargs)
        if not cls.__name__.startswith("Abstract"):
            cls = dataclasses.dataclass(frozen=True)(cls)
            fields = dataclasses.fields(cls)
            static = [field.name for field in fields if field.metadata.get("static", False)]
            data = [field.name for field in fields if field.name not in static]
            jax.tree_util.register_dataclass(cls, data_fields=data, meta_fields=static)

    def init(self, dimension, dtype):
        raise NotImplementedError

    def step(self, state, hessian, gradient):
        raise NotImplementedError

    def update(self, state, gain_ratio, finite, actual, cost):
        raise NotImplementedError

    def diverged(self, state, cost, initial_cost):
        raise NotImplementedError

    def damping(self, state) -> jax.Array:
        r"""The damping $\mu$ of the current state (zero for undamped solvers), for the log."""
        raise NotImplementedError

    def scale(self, state) -> jax.Array:
        """The scaling $d$ of the variables the last step was computed with (see the module
        docstring)."""
        raise NotImplementedError


class GaussNewton(AbstractSolver):
    r"""Gauss-Newton: $J^\top W J\,\delta = -J^\top W r$, every step taken.

    Fast near a solution of a small-residual problem, with no safeguard far from one. A singular
    $J^\top W J$ (an unconstrained gauge, a variable no residual touches) is regularized (see
    `cholesky_with_fallback`) so the step is the minimum-norm one in Jacobi-scaled variables.
    The stopping rules see unscaled variables (`scale` is all ones).

    **Arguments:**

    - `divergence_factor`: stop with `Status.DIVERGED` when the cost exceeds this multiple of the
      initial cost.
    """

    rejects_steps = False
    divergence_factor: float = 1e6

    def init(self, dimension, dtype):
        return jnp.ones((dimension,), dtype)

    def step(self, state, hessian, gradient):
        return solve_spd(hessian, -gradient), state

    def update(self, state, gain_ratio, finite, actual, cost):
        return finite, state

    def diverged(self, state, cost, initial_cost):
        return trust_region.cost_diverged(cost, initial_cost, self.divergence_factor)

    def damping(self, state):
        return jnp.zeros(())

    def scale(self, state):
        return state


class LevenbergMarquardt(AbstractSolver):
    r"""Levenberg-Marquardt: $(J^\top W J + \mu D^2)\,\delta = -J^\top W r$ with a diagonal
    scaling $D$ of the variables; a step with gain ratio $\varrho \ge$ `min_gain_ratio` is kept.

    The one options object of lieax's Levenberg-Marquardt, for both doors:
    `lieax.lstsq.least_squares(..., solver=...)` (dense) and
    `lieax.factorgraph.FactorGraph.solve(solver=...)` (block-sparse; it supports the scalings
    `"identity"`, `"clipped"` and `"jacobi"` and the damping updates `"gtsam"` and
    `"nielsen"`, and refuses the others with a `ValueError`). When they stop is the other
    options object, `lieax.lstsq.Termination`. The presets reproduce the defaults of the
    libraries they name: `LevenbergMarquardt.gtsam()` (`FactorGraph.solve`'s and
    `lieax.graph.optimize`'s default), `LevenbergMarquardt.ceres()` and
    `LevenbergMarquardt.minpack()`; each takes keyword changes, e.g.
    `LevenbergMarquardt.gtsam(scaling="clipped", damping_update="nielsen")` (GTSAM's diagonal
    damping with Nielsen's rule, as its `ceresDefaults()`). `LevenbergMarquardt()` is
    `least_squares`' default: MINPACK's scaling with Nielsen's rule and Ceres' constants.

    `damping_update` chooses how the damping $\mu$ follows $\varrho$:

    - `"nielsen"` (default): Nielsen's rule, a kept step sets
      $\mu \leftarrow \mu \max(\tfrac13, 1 - (2\varrho - 1)^3)$, $\nu \leftarrow 2$; a
      rejected one $\mu \leftarrow \nu\mu$, $\nu \leftarrow 2\nu$ (Madsen, Nielsen,
      Tingleff, "Methods for non-linear least squares problems", 2004, Sec. 3.2; the rule of
      `lieax.factorgraph`'s loop too: both call `_trust_region.nielsen`).
    - `"minpack"`: MINPACK's trust region (`lmder`, Moré 1978): a radius $\Delta$ on
      $\|D\delta\|$, halved or cut to as little as a tenth after a poor step
      ($\varrho \le \tfrac14$), set to $2\|D\delta\|$ after a good one
      ($\varrho \ge \tfrac34$; `_trust_region.minpack`), and $\mu$ the smallest damping
      whose step fits, $\|D\delta\| \le 1.1\,\Delta$ (`lmpar`,
      `_normal_equations.damping_for_radius`): 0 (the Gauss-Newton step) when that fits, so
      that the last steps are Newton's. $\Delta$ starts infinite: the first step is
      Gauss-Newton's and its length is the first radius (MINPACK starts from
      $\Delta = 100\,\|D x_0\|$, which a group element gives no meaning to). Each step
      factors the normal equations a few times (MINPACK's Newton iteration on $\mu$, at most
      ten tries) instead of once. From NIST's first start of MGH10 it reaches the certified
      values, where Nielsen's rule stalls in the valley $b_1 \to 0$; on the NIST problems of
      `tests/test_lstsq_scaling.py` it mostly evaluates the residual as often as MINPACK
      (`benchmarks/regression.py`), and solves 46 of the 48 cases to Nielsen's 44; but from
      MGH17's first start it crawls along a valley and needs more than 1,000 iterations under
      `vmap` (1,534; 381 unbatched, where rounding differs), which Nielsen's rule does not
      (569), so it is not the default. `initial_damping` and `min_damping` play no part.
    - `"gtsam"`: GTSAM 4.3's rule (`LevenbergMarquardtOptimizer` with `useFixedLambdaFactor`):
      $\mu \leftarrow \mu / f$ after a kept step, $\mu f$ after a rejected one,
      $f$ = `damping_factor` (`_trust_region.gtsam`). With the Marquardt diagonal it
      ping-pongs between two values of $\mu$ (see `lieax.factorgraph._solve`), so pair it with
      `scaling="identity"`, as GTSAM does.

    The system is solved in scaled variables $\tilde\delta = S^{-1}\delta$:
    $(S H S + \mu \tilde D)\,\tilde\delta = -S g$, $\delta = S\tilde\delta$
    ($H = J^\top W J$, $g = J^\top W r$, $D^2 = S^{-1} \tilde D S^{-1}$), so that its Cholesky
    factorization (and the regularization of a singular one) does not see the units of the
    unknowns. With $c_j = \|W^{1/2} J_{:,j}\|$ the norms of
    the Jacobian's columns, `scaling` chooses $S$ and $\tilde D$:

    - `"minpack"` (default): $S = \mathrm{diag}(1/d)$, $\tilde D = I$, with $d_j$ the largest
      $c_j$ of every linearization so far ($d_j = 1$ while it is zero): MINPACK's `lmder` in
      mode 1 (Moré, "The Levenberg-Marquardt algorithm: implementation and theory", 1978,
      Sec. 6), with either damping rule. Invariant under $x_j \to a_j x_j$.
    - `"jacobi"`: $S = \mathrm{diag}(1/(1 + c_j))$ and
      $\tilde D = \mathrm{diag}(S H S)$ clipped to `[min_diagonal, max_diagonal]`: Ceres'
      `jacobi_scaling` with its Levenberg-Marquardt strategy (`trust_region_minimizer.cc`,
      `levenberg_marquardt_strategy.cc`). The $1$ in $1 + c_j$ leaves columns of norm below
      about 1 unscaled.
    - `"clipped"`: $S = I$, $\tilde D = \mathrm{diag}(H)$ clipped to
      `[min_diagonal, max_diagonal]` (Marquardt's diagonal: lieax's damping before the scaling
      option; Ceres without `jacobi_scaling`; GTSAM's `diagonalDamping`). The clip is absolute:
      it misjudges columns whose norms span many orders of magnitude
      (`tests/test_lstsq_scaling.py`).
    - `"identity"`: $S = I$, $\tilde D = I$: $\mu I$, GTSAM's default damping; $\mu$ is in
      the units of $H$.

    `scale` is $d$ (`"minpack"`), $1 + c$ (`"jacobi"`) or ones (`"clipped"`, `"identity"`).

    Only `"minpack"` is invariant under a constant factor on the residual (every term of its
    system scales alike; powers of two leave its iterates unchanged bit for bit,
    `tests/test_lstsq_faults.py`). The `min_diagonal` clip of `"jacobi"` and `"clipped"` is
    absolute, as Ceres' `min_lm_diagonal`: for a residual scaled down by $10^{-12}$ the clip sets
    the damping, the steps become tiny and the tolerances end the solve `CONVERGED` after one
    iteration with the start barely moved (Rosenbrock's problem scaled by $10^{-12}$), as Ceres
    would. Use them on residuals of order one.

    **Arguments:**

    - `initial_damping`: $\mu$ at the first iteration (Ceres' initial trust radius $10^4$ is
      $\mu = 10^{-4}$).
    - `min_gain_ratio`: the smallest gain ratio of an accepted step.
    - `min_damping`, `max_damping`: bounds of $\mu$; reaching `max_damping` without converging
      stops the solve with `Status.DIVERGED`.
    - `min_diagonal`, `max_diagonal`: bounds of $\tilde D$ for `"jacobi"` and `"clipped"`.
    - `damping_factor`: $f$ of `damping_update="gtsam"` (GTSAM's `lambdaFactor`).
    - `scaling`: `"minpack"`, `"jacobi"`, `"clipped"` or `"identity"` (static: each compiles its
      own solve).
    - `damping_update`: `"nielsen"`, `"minpack"` or `"gtsam"` (static).
    - `inclusive_gain_ratio`: a step is kept when $\varrho \ge$ `min_gain_ratio` (True,
      MINPACK's `ratio >= p0001`) or $\varrho >$ `min_gain_ratio` (False, GTSAM's
      `modelFidelity > minModelFidelity`, Ceres' `relative_decrease > min_relative_decrease`)
      (static).
    - `inclusive_max_damping`: the solve gives up when $\mu \ge$ `max_damping` (True,
      GTSAM's `lambda >= lambdaUpperBound`) or $\mu >$ `max_damping` (False, Ceres' trust
      radius below `min_trust_region_radius`) (static).

    | preset | scaling | damping update | `initial_damping` | `max_damping` | `min_gain_ratio` | inclusive: gain ratio, max damping |
    |---|---|---|---|---|---|---|
    | `LevenbergMarquardt()` | `"minpack"` | `"nielsen"` | $10^{-4}$ | $10^{32}$ | $10^{-3}$ | $\ge$, $>$ |
    | `.gtsam()` (GTSAM 4.3) | `"identity"` | `"gtsam"`, ×10 | $10^{-5}$ | $10^{5}$ | $10^{-3}$ | $>$, $\ge$ |
    | `.ceres()` (Ceres 2) | `"jacobi"` | `"nielsen"` | $10^{-4}$ | $10^{32}$ | $10^{-3}$ | $>$, $>$ |
    | `.minpack()` (`lmder`) | `"minpack"` | `"minpack"` | unused | $10^{32}$ | $10^{-4}$ | $\ge$, $>$ |

    `.gtsam()` has `min_damping=0` (GTSAM's `lambdaLowerBound`); the others $10^{-16}$ (Ceres'
    `max_trust_region_radius` $10^{16}$).
    """

    rejects_steps = True
    initial_damping: float = 1e-4
    min_gain_ratio: float = 1e-3
    min_damping: float = 1e-16
    max_damping: float = 1e32
    min_diagonal: float = 1e-6
    max_diagonal: float = 1e32
    damping_factor: float = 10.0
    scaling: str = dataclasses.field(default="minpack", metadata={"static": True})
    damping_update: str = dataclasses.field(default="nielsen", metadata={"static": True})
    inclusive_gain_ratio: bool = dataclasses.field(default=True, metadata={"static": True})
    inclusive_max_damping: bool = dataclasses.field(default=False, metadata={"static": True})

    @classmethod
    def gtsam(cls, **changes) -> "LevenbergMarquardt":
        r"""GTSAM 4.3's `LevenbergMarquardtParams` defaults: $\mu I$, $\mu_0 = 10^{-5}$, ×10 on
        a rejection and ÷10 on a kept step, give up at $10^5$, a step kept when its gain ratio
        exceeds $10^{-3}$ (`changes`: fields to set otherwise)."""
        preset = dict(
            scaling="identity", damping_update="gtsam", initial_damping=1e-5, damping_factor=10.0,
            max_damping=1e5, min_damping=0.0, min_gain_ratio=1e-3, inclusive_gain_ratio=False,
            inclusive_max_damping=True,
        )  # fmt: skip
        return cls(**{**preset, **changes})

    @classmethod
    def ceres(cls, **changes) -> "LevenbergMarquardt":
        r"""Ceres 2's `Solver::Options` defaults for Levenberg-Marquardt: `jacobi_scaling`,
        Nielsen's rule from the trust radius $10^4$ ($\mu_0 = 10^{-4}$), the diagonal clipped
        to `[1e-6, 1e32]`, a step kept when its relative decrease exceeds
        `min_relative_decrease` $10^{-3}$ (`changes`: fields to set otherwise)."""
        preset = dict(scaling="jacobi", damping_update="nielsen", inclusive_gain_ratio=False)
        return cls(**{**preset, **changes})

    @classmethod
    def minpack(cls, **changes) -> "LevenbergMarquardt":
        """MINPACK's `lmder` in mode 1: the running maximum of the column norms as scaling, its
        trust-region radius and `lmpar`'s damping, a step kept when its gain ratio is at least
        $10^{-4}$ (`changes`: fields to set otherwise)."""
        return cls(**{"scaling": "minpack", "damping_update": "minpack", "min_gain_ratio": 1e-4,
                      **changes})  # fmt: skip

    def __post_init__(self):
        if self.scaling not in _SCALINGS:
            raise ValueError(
                f"LevenbergMarquardt: scaling must be one of {_SCALINGS}, got {self.scaling!r}."
            )
        if self.damping_update not in _DAMPING_UPDATES:
            raise ValueError(
                f"LevenbergMarquardt: damping_update must be one of {_DAMPING_UPDATES}, got "
                f"{self.damping_update!r}."
            )

    def init(self, dimension, dtype):
        initial_scale = jnp.zeros if self.scaling == "minpack" else jnp.ones
        if self.damping_update == "minpack":  # (damping, radius, scale, |D step|, g . step)
            zero = jnp.zeros((), dtype)
            radius = jnp.asarray(jnp.inf, dtype)
            return (zero, radius, initial_scale((dimension,), dtype), zero, zero)
        return (  # (damping, Nielsen's factor, scale)
            jnp.asarray(self.initial_damping, dtype),
            jnp.asarray(2.0, dtype),
            initial_scale((dimension,), dtype),
        )

    def step(self, state, hessian, gradient):
        damping, factor, scale = state[:3]  # `factor` is the radius for "minpack"
        # the scaling chooses the path, not the optimum: not differentiated (and sqrt is not
        # differentiable at a zero column)
        norms = jnp.sqrt(jnp.maximum(jax.lax.stop_gradient(jnp.diagonal(hessian)), 0.0))
        if self.scaling == "minpack":
            scale = jnp.maximum(scale, norms)
            scale = jnp.where(scale > 0, scale, 1.0)
        elif self.scaling == "jacobi":
            scale = 1.0 + norms
        scaled = hessian / (scale[:, None] * scale[None, :])
        if self.scaling in ("minpack", "identity"):
            diagonal = jnp.ones_like(scale)
        else:
            diagonal = jnp.clip(jnp.diagonal(scaled), self.min_diagonal, self.max_diagonal)
        rhs = -gradient / scale
        if self.damping_update == "minpack":  # in the variables D step, where the damping is mu I
            root = jnp.sqrt(diagonal)
            damping = damping_for_radius(
                scaled / (root[:, None] * root[None, :]), rhs / root, factor, damping
            )
        scaled_step = solve_spd(scaled + jnp.diag(damping * diagonal), rhs)
        step = scaled_step / scale
        if self.damping_update == "minpack":
            step_norm = jnp.sqrt(jnp.sum(diagonal * jax.lax.stop_gradient(scaled_step) ** 2))
            slope = jax.lax.stop_gradient(gradient @ step)
            radius = jnp.where(jnp.isinf(factor), step_norm, factor)
            return step, (damping, radius, scale, step_norm, slope)
        return step, (damping, factor, scale)

    def update(self, state, gain_ratio, finite, actual, cost):
        damping, factor, scale = state[:3]
        accept = finite & trust_region.accepts(
            gain_ratio, self.min_gain_ratio, inclusive=self.inclusive_gain_ratio
        )
        if self.damping_update == "minpack":
            step_norm, slope = state[3:]
            factor, damping = trust_region.minpack(
                finite, gain_ratio, actual, cost, slope, step_norm, factor, damping
            )
            damping = jnp.minimum(damping, 2.0 * self.max_damping)
            return accept, (damping, factor, scale, step_norm, slope)
        if self.damping_update == "gtsam":
            damping = trust_region.gtsam(accept, damping, self.damping_factor)
        else:
            damping, factor = trust_region.nielsen(accept, gain_ratio, damping, factor)
        damping = jnp.clip(damping, self.min_damping, 2.0 * self.max_damping)
        return accept, (damping, factor.astype(damping.dtype), scale)

    def diverged(self, state, cost, initial_cost):
        return trust_region.damping_exhausted(
            state[0], self.max_damping, inclusive=self.inclusive_max_damping
        )

    def damping(self, state):
        return state[0]

    def scale(self, state):
        return jnp.where(state[2] > 0, state[2], 1.0)
