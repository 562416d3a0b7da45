"""Gauss-Newton and Levenberg-Marquardt: how a step is computed from the normal equations and
whether it is kept.

A solver is a pytree (its numeric settings are leaves, so they may be traced) whose methods the
loop of `least_squares` calls:

- `init(dtype)`: its state (damping and the like) at the first iterate;
- `step(state, hessian, gradient)`: the step $\\delta$ in flattened tangent coordinates;
- `update(state, gain_ratio, finite)`: whether the trial point $x \\oplus \\delta$ is kept, and
  the next state, from the gain ratio $\\varrho$ (actual over predicted decrease of the cost);
- `diverged(state, cost, initial_cost)`: whether to stop with `Status.DIVERGED`;
- `damping(state)`: the damping, for the iteration table.

`rejects_steps` says whether a rejected (non-finite) trial point is an ordinary event
(Levenberg-Marquardt shrinks the step and tries again) or the end of the solve (Gauss-Newton).
"""

import dataclasses
from typing import ClassVar

import jax
import jax.numpy as jnp

from ._normal_equations import solve_spd


class AbstractSolver:
    """Base of the dense normal-equation solvers; see the module docstring for the interface."""

    rejects_steps: ClassVar[bool]

    def __init_subclass__(cls, **kwargs):
        super().__init_subclass__(**kwargs)
        if not cls.__name__.startswith("Abstract"):
            cls = dataclasses.dataclass(frozen=True)(cls)
            names = [field.name for field in dataclasses.fields(cls)]
            jax.tree_util.register_dataclass(cls, data_fields=names, meta_fields=[])

    def init(self, dtype):
        raise NotImplementedError

    def step(self, state, hessian, gradient):
        raise NotImplementedError

    def update(self, state, gain_ratio, finite):
        raise NotImplementedError

    def diverged(self, state, cost, initial_cost):
        raise NotImplementedError

    def damping(self, state) -> jax.Array:
        """The damping $\\mu$ of the current state (zero for undamped solvers), for the log."""
        raise NotImplementedError


class GaussNewton(AbstractSolver):
    """Gauss-Newton: $J^\\top W J\\,\\delta = -J^\\top W r$, every step taken.

    Fast near a solution of a small-residual problem, with no safeguard far from one. A singular
    $J^\\top W J$ (an unconstrained gauge, a variable no residual touches) is regularized (see
    `cholesky_with_fallback`) so the step is the minimum-norm one.

    **Arguments:**
    - `divergence_factor`: stop with `Status.DIVERGED` when the cost exceeds this multiple of the
      initial cost.
    """

    rejects_steps = False
    divergence_factor: float = 1e6

    def init(self, dtype):
        return ()

    def step(self, state, hessian, gradient):
        return solve_spd(hessian, -gradient)

    def update(self, state, gain_ratio, finite):
        return finite, state

    def diverged(self, state, cost, initial_cost):
        return cost > self.divergence_factor * initial_cost

    def damping(self, state):
        return jnp.zeros(())


class LevenbergMarquardt(AbstractSolver):
    """Levenberg-Marquardt: $(J^\\top W J + \\mu D)\\,\\delta = -J^\\top W r$, with
    $D = \\mathrm{diag}(J^\\top W J)$ clipped to `[min_diagonal, max_diagonal]` (Marquardt's
    scaling, as Ceres), and the damping $\\mu$ adapted from the gain ratio $\\varrho$ by Nielsen's
    rule: a step with $\\varrho \\ge$ `min_gain_ratio` is kept and
    $\\mu \\leftarrow \\mu \\max(\\tfrac13, 1 - (2\\varrho - 1)^3)$, $\\nu \\leftarrow 2$;
    otherwise it is rejected and $\\mu \\leftarrow \\nu\\mu$, $\\nu \\leftarrow 2\\nu$ (Madsen,
    Nielsen, Tingleff, "Methods for non-linear least squares problems", 2004, Sec. 3.2).

    **Arguments:**
    - `initial_damping`: $\\mu$ at the first iteration (Ceres' initial trust radius $10^4$ is
      $\\mu = 10^{-4}$).
    - `min_gain_ratio`: the smallest gain ratio of an accepted step.
    - `min_damping`, `max_damping`: bounds of $\\mu$; reaching `max_damping` without converging
      stops the solve with `Status.DIVERGED`.
    - `min_diagonal`, `max_diagonal`: bounds of the scaling $D$.
    """

    rejects_steps = True
    initial_damping: float = 1e-4
    min_gain_ratio: float = 1e-3
    min_damping: float = 1e-16
    max_damping: float = 1e32
    min_diagonal: float = 1e-6
    max_diagonal: float = 1e32

    def init(self, dtype):
        return (jnp.asarray(self.initial_damping, dtype), jnp.asarray(2.0, dtype))

    def step(self, state, hessian, gradient):
        damping, _ = state
        scaling = jnp.clip(jnp.diagonal(hessian), self.min_diagonal, self.max_diagonal)
        return solve_spd(hessian + jnp.diag(damping * scaling), -gradient)

    def update(self, state, gain_ratio, finite):
        damping, factor = state
        accept = finite & (gain_ratio >= self.min_gain_ratio)
        shrink = jnp.maximum(1.0 / 3.0, 1.0 - (2.0 * gain_ratio - 1.0) ** 3)
        damping = jnp.where(accept, damping * shrink, damping * factor)
        factor = jnp.where(accept, 2.0, 2.0 * factor)
        damping = jnp.clip(damping, self.min_damping, 2.0 * self.max_damping)
        return accept, (damping, factor.astype(damping.dtype))

    def diverged(self, state, cost, initial_cost):
        damping, _ = state
        return damping > self.max_damping

    def damping(self, state):
        return state[0]
