r"""`least_squares`: the dense solve loop, compiled once as a `lax.while_loop`, with its stopping
rules, its tolerances and the verbose iteration table.

Each iteration evaluates the cost, $H = J^\top W J$ and $g = J^\top W r$ at the trial point
$x \oplus \delta$ the previous iteration chose (one linearization of the residual; the first
iteration evaluates $x_0$), keeps or rejects it on the gain ratio
$\varrho = (c(x) - c(x \oplus \delta)) / (-g^\top\delta - \tfrac12 \delta^\top H \delta)$
(the solver's `update`), checks the stopping rules, and solves the normal equations at the kept
point for the next step. The gain ratio, the acceptance and damping rules and the precedence of
the status codes are `_trust_region`'s, and the order of the iteration's phases is
`_iteration.body`'s, both shared with the factor-graph loop; this loop's own are its dense linear
algebra, its MINPACK-style stopping tests (scaled step, gradient cosine, relative cost change)
and its treatment of a decrease below the cost's rounding error (the step is trusted).
Every problem of a `vmap` runs this same loop in lockstep; a problem that has stopped keeps its
state while the others run on (the batching rule of `while_loop`).
"""

import dataclasses
import functools
from collections.abc import Callable
from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax

from .._runtime_error import raise_if
from .._typing import PyTree
from ..autodiff._tangents import (
    check_retraction,
    leaf_array,
    leaf_tangent_shape,
    manifold_leaves,
    rplus,
    tangent_dim,
    unflatten_tangents,
)
from ..groups import AbstractManifold
from ..retractions import Retraction, exp
from . import _iteration
from . import _trust_region as trust_region
from ._implicit import with_implicit_derivatives
from ._losses import AbstractLoss
from ._problem import linearize
from ._solution import (
    NonFiniteStartError,
    Solution,
    SolveError,
    Status,
    is_failure,
    nonfinite_leaves,
)
from ._solvers import AbstractSolver, LevenbergMarquardt
from ._termination import Termination

_DEFAULT_TOLERANCE = {np.dtype(np.float64): 1e-10, np.dtype(np.float32): 1e-6}
_DIFFERENTIATION = ("implicit", "unrolled")
_LEVENBERG_MARQUARDT = LevenbergMarquardt()  # the default solver (immutable, so shared)
_TERMINATION = Termination()  # the default stopping rules (immutable, so shared)


def least_squares(
    residual_fn: Callable[[PyTree, PyTree], PyTree],
    x0: PyTree,
    args: PyTree | None = None,
    *,
    solver: AbstractSolver = _LEVENBERG_MARQUARDT,
    loss: PyTree | None = None,
    termination: Termination = _TERMINATION,
    differentiation: str = "implicit",
    retraction: Retraction = exp,
    verbose: bool = False,
    throw: bool = True,
) -> Solution:
    r"""Minimizes $\tfrac12 \sum_i \rho(\|r_i(x, \text{args})\|^2)$ over a state `x` that
    mixes group elements and arrays, every update a retraction $x \leftarrow x \oplus \delta$
    ($x \leftarrow \mathcal{R}_x(\delta)$ with another `retraction`).

    **Arguments:**

    - `residual_fn`: `residual_fn(x, args)` returns an array or a pytree of arrays (typically one
      residual per data element, built with `jax.vmap` over the data). A leaf of shape
      `(*batch, k)` holds `k`-dimensional blocks; a leaf with fewer than two axes holds scalar
      blocks. The solve is compiled once per `residual_fn` object: define it once, not as a new
      lambda on every call.
    - `x0`: the initial state, a pytree of lieax groups and floating arrays.
    - `args`: data passed to `residual_fn`, a pytree of arrays; differentiable (see below).
    - `solver`: `LevenbergMarquardt()` (default) or `GaussNewton()`.
    - `loss`: `None`, a robust loss (`Huber`, `Cauchy`, `Tukey`, `GemanMcClure`), or a pytree
      prefix of the residual with a loss or `None` per leaf. Applied by reweighting.
    - `termination`: when to stop, a `Termination` (`counting="trials"`: every trial point is an
      iteration, rejected steps included). Default `Termination()`: 100 iterations, the
      tolerances $10^{-10}$ in float64 and $10^{-6}$ in float32 (`None` reads as these);
      `Termination.ceres()` and `Termination.minpack()` are their peers' defaults. Converged
      when a kept step changes the cost by less than `function_tolerance` times it (or by less
      than `absolute_function_tolerance`), when a rejected step was predicted to decrease it by
      less than `function_tolerance` times it, when
      $\max_j |g_j| / (c_j \|r\|) \le$ `gradient_tolerance` (the largest cosine between the
      weighted residual and a Jacobian column, $g = J^\top W r$, $c_j$ the column's norm,
      $\|r\| = \sqrt{2\,\text{cost}}$: MINPACK's `gtol`; a zero residual passes), or when a step
      has $\|D\delta\| \le \text{tol}\,(\|D|x|\| + \text{tol}\,\|d\|/\sqrt{n})$,
      tol = `parameter_tolerance`, $D = \mathrm{diag}(d)$ the solver's scaling
      (`AbstractSolver.scale`), $|x|$ the state's magnitude per tangent coordinate (a group
      element's parameter norm spread over its coordinates), $n$ the tangent dimension
      (MINPACK's `xtol`; with $D = I$: $\|\delta\| \le \text{tol}\,(\|x\| + \text{tol})$).
      A tolerance of 0 turns its test off. At `x0` only an exactly zero gradient stops the solve
      (`iterations == 0`). Every test but the absolute one is relative: multiplying the residual
      by a constant changes neither the iterates (up to rounding) nor the status with
      `LevenbergMarquardt()` or `GaussNewton()`. A new tolerance reuses the compiled solve
      (they are traced); `max_iterations` compiles its own.
    - `differentiation`: `"implicit"` (default): derivatives of `value` and `cost` with respect
      to `args` (and the loss's scale) by the implicit function theorem at the solution, with no
      iteration unrolled; the start `x0` gets zero derivative, and a solve that did not converge
      gets the derivative of the point it returned as if it were the optimum. `"unrolled"`: the
      loop runs as a `lax.scan` of `termination.max_iterations + 1` masked iterations and JAX differentiates
      through it (for comparison: every iteration runs, and reverse mode stores them all).
    - `retraction`: how a step moves the state, from `lieax.retractions`: `exp` (default,
      $X\,\mathrm{Exp}(\delta)$), `cayley` (SO3, SE3) or `first_order` (SE3); leaves it has
      no rule for move by `exp`. The Jacobians are the same (every retraction's derivative at
      $\delta = 0$ is the identity), and so is the optimum (a zero of the gradient); the
      iterates differ at second order in the step. Compiled once per retraction.
    - `verbose`: print an iteration table (cost, cost change, the gradient and step norms that
      the stopping rules compare with their tolerances, gain ratio, damping) from inside the
      compiled loop. Under `vmap` every problem prints its rows, the
      problems' rows interleaved.
    - `throw`: raise `SolveError` when the solve ends `DIVERGED` or `NONFINITE` (this waits for
      the result); `NonFiniteStartError` (a `SolveError` and a `ValueError`) when the start
      was not finite, naming the input (`x0`, `args` or a loss's scale) by its pytree path.
      Under `jit` the error is raised when the compiled program runs (JAX's runtime error,
      carrying the `SolveError`'s message); under `vmap` nothing is raised and
      `Solution.status` says what happened for each problem, as with `throw=False`.

    A non-finite start (NaN or infinity in `x0`, in `args` where the residual reads them, or a
    loss scale that is not positive and finite) is not solved: the `Solution` holds `x0`
    unchanged, `iterations == 0` and `Status.NONFINITE` (the start is what the caller gave;
    an invented finite value would be a silently wrong answer). A non-finite residual met later
    ends the solve `NONFINITE` with `iterations > 0` and the last finite iterate. Under `vmap`
    each problem stops on its own: one bad problem does not change the others' results.

    **Returns:** a `Solution` (`value`, `cost`, `iterations`, `status`, `cost_history`).

    Example (a rotation that maps `source` onto `target`, both of shape `(N, 3)`):
    ```python
    def residual(rotation, data):
        source, target = data
        return jax.vmap(lambda p, q: rotation @ p - q)(source, target)

    solution = lieax.lstsq.least_squares(residual, lieax.SO3.identity(), (source, target))
    ```
    """
    _check_arguments(residual_fn, solver, termination, differentiation, loss)
    leaves, _ = manifold_leaves(x0, "x0")
    dtype = np.dtype(jnp.result_type(*(leaf_array(leaf) for leaf in leaves)))
    solution = _solve(
        residual_fn,
        bool(verbose),
        differentiation,
        check_retraction(retraction),
        x0,
        args,
        solver,
        loss,
        _with_default_tolerances(termination, dtype),
    )
    if throw:
        solution = _raise_on_failure(solution, x0, args, loss)
    return solution


def _check_arguments(residual_fn, solver, termination, differentiation, loss):
    """A `TypeError` or `ValueError` naming the first argument of `least_squares` that it cannot
    take (`termination`: one whose counting or tests this loop does not run)."""
    if not callable(residual_fn):
        raise TypeError(f"residual_fn must be callable, got {residual_fn!r}.")
    if not isinstance(solver, AbstractSolver):
        raise TypeError(
            f"solver must be a lieax.lstsq solver (e.g. LevenbergMarquardt()), got {solver!r}."
        )
    if not isinstance(termination, Termination):
        raise TypeError(f"termination must be a lieax.lstsq.Termination, got {termination!r}.")
    termination.require("least_squares", "trials")
    if differentiation not in _DIFFERENTIATION:
        raise ValueError(
            f"differentiation must be one of {_DIFFERENTIATION}, got {differentiation!r}."
        )
    _check_loss(loss)


def _with_default_tolerances(termination, dtype) -> Termination:
    """`termination` with its `None` tolerances set to the dtype's default ($10^{-10}$ in
    float64, $10^{-6}$ otherwise), kept by `(termination, dtype)` (building one takes tens of
    microseconds, a lookup one: a loop of small solves calls this every time)."""
    try:
        return _cached_resolve(termination, dtype)
    except TypeError:  # an array tolerance: not hashable, built every time
        return _resolve(termination, dtype)


def _resolve(termination, dtype) -> Termination:
    default = _DEFAULT_TOLERANCE.get(dtype, _DEFAULT_TOLERANCE[np.dtype(np.float32)])
    names = ("function_tolerance", "gradient_tolerance", "parameter_tolerance")
    unset = {name: default for name in names if getattr(termination, name) is None}
    return dataclasses.replace(termination, **unset) if unset else termination


_cached_resolve = functools.lru_cache(maxsize=64)(_resolve)


def _check_loss(loss):
    is_leaf = lambda node: node is None or isinstance(node, AbstractLoss)  # noqa: E731
    for leaf in jax.tree_util.tree_leaves(loss, is_leaf=is_leaf):
        if not (leaf is None or isinstance(leaf, AbstractLoss)):
            raise TypeError(
                f"loss must be None, a lieax.lstsq loss (Huber, Cauchy, Tukey, GemanMcClure) or a "
                f"pytree of them, got {leaf!r}."
            )


class _State(NamedTuple):
    x: object  # the current (last accepted) point
    cost: jax.Array
    hessian: jax.Array  # J^T W J at x, flattened tangent coordinates
    gradient: jax.Array  # J^T W r at x
    solver_state: object
    x_trial: object  # x ⊕ step, evaluated by the next iteration
    step: jax.Array
    first: jax.Array  # the next evaluation is the one of x0
    iteration: jax.Array
    status: jax.Array
    cost_history: jax.Array


def _all_finite(*arrays):
    return jnp.all(jnp.stack([jnp.all(jnp.isfinite(a)) for a in arrays]))


def _tree_where(condition, new, old):
    return jax.tree_util.tree_map(lambda a, b: jnp.where(condition, a, b), new, old)


def _parameter_magnitudes(x):
    r"""$|x_j|$ per flattened tangent coordinate, for the step test: an array's entries' absolute
    values; a group element's parameter norm over $\sqrt{\text{dof}}$ on each of its coordinates
    (so that the squares sum to the squared norm of its parameters)."""
    leaves, _ = manifold_leaves(lax.stop_gradient(x), "x")
    parts = []
    for leaf in leaves:
        if isinstance(leaf, AbstractManifold):
            norm = jnp.sqrt(jnp.sum(leaf_array(leaf) ** 2, axis=-1, keepdims=True))
            norm = jnp.broadcast_to(norm / np.sqrt(leaf.tangent_dim), leaf_tangent_shape(leaf))
            parts.append(jnp.ravel(norm))
        else:
            parts.append(jnp.ravel(jnp.abs(leaf)))
    return jnp.concatenate(parts) if parts else jnp.zeros((0,))


def _gain_ratio(values, trial_finite):
    r"""$\varrho = (c - c_t) / (-g^\top\delta - \tfrac12 \delta^\top H \delta)$, the actual
    decrease $c - c_t$ ($c_t$ the cost at the trial point) and the predicted one (the
    denominator); $\varrho = -\infty$ for a non-finite trial point. Below the rounding error
    of the cost the ratio is noise: it is taken as 1 (trust the model) unless the cost
    measurably rose, which lets the last Newton-like steps through."""
    cost, cost_trial, step, hessian, gradient = values
    actual = cost - cost_trial
    predicted = -(gradient @ step + 0.5 * step @ (hessian @ step))
    ratio = jnp.where(
        trial_finite & (predicted > 0), trust_region.gain_ratio(actual, predicted), -jnp.inf
    )
    resolution = 16 * jnp.finfo(cost.dtype).eps * jnp.abs(cost)
    unmeasurable = trial_finite & (jnp.abs(predicted) <= resolution) & (actual >= -resolution)
    return jnp.where(unmeasurable, 1.0, ratio), actual, predicted


@jax.jit(static_argnums=(0, 1, 2, 3))
def _solve(residual_fn, verbose, differentiation, retraction, x0, args, solver, loss, termination):
    implicit = differentiation == "implicit"
    if implicit:  # the loop is not differentiated: derivatives come from with_implicit_derivatives
        x0, args_loop, loss_loop = lax.stop_gradient((x0, args, loss))
    else:
        args_loop, loss_loop = args, loss
    phases = _DensePhases(
        residual_fn, solver, retraction, x0, args_loop, loss_loop, termination, verbose
    )
    # implicit: a `while_loop`; unrolled: a fixed number of masked iterations, so that reverse
    # mode can go through them
    final = _iteration.run(
        phases, phases.initial_state(x0), None if implicit else termination.max_iterations + 1
    )
    sg = lax.stop_gradient
    if verbose:
        jax.debug.callback(
            _print_summary, final.status, final.iteration, final.cost_history[0], sg(final.cost)
        )
    value, cost = final.x, final.cost
    if implicit:
        value, cost = with_implicit_derivatives(residual_fn, value, cost, (args, loss))
    return Solution(
        value=value,
        cost=cost,
        iterations=final.iteration,
        status=final.status,
        cost_history=final.cost_history,
    )


class _DensePhases:
    """The five phases of `_iteration.body` for the dense normal equations of one state (see the
    module docstring): one linearization per iteration, at the trial point the previous
    iteration chose; the first iteration evaluates $x_0$ (so the residual is traced and
    compiled once). Decisions are not differentiated, they only select between differentiable
    values."""

    def __init__(self, residual_fn, solver, retraction, x0, args, loss, termination, verbose):
        self.residual_fn, self.solver, self.retraction = residual_fn, solver, retraction
        self.args, self.loss, self.termination = args, loss, termination
        self.max_iterations, self.verbose = termination.max_iterations, verbose
        self.n = tangent_dim(x0)
        x0_arrays = [leaf_array(leaf) for leaf in manifold_leaves(x0, "x0")[0]]
        self.dtype = jnp.result_type(*x0_arrays)
        self.start_finite = _all_finite(*x0_arrays)  # a NaN the residual does not read counts too

    def initial_state(self, x0):
        n, dtype = self.n, self.dtype
        return _State(
            x=x0,
            cost=jnp.zeros((), dtype),
            hessian=jnp.zeros((n, n), dtype),
            gradient=jnp.zeros((n,), dtype),
            solver_state=self.solver.init(n, dtype),
            x_trial=x0,
            step=jnp.zeros((n,), dtype),
            first=jnp.ones((), bool),
            iteration=jnp.zeros((), jnp.int32),
            status=jnp.asarray(Status.RUNNING, jnp.int32),
            cost_history=jnp.full((self.max_iterations + 1,), jnp.nan, dtype),
        )

    def evaluate(self, state: _State):
        cost, hessian, gradient = linearize(self.residual_fn, state.x_trial, self.args, self.loss)
        finite = _all_finite(cost, hessian, gradient) & (~state.first | self.start_finite)
        return {"cost": cost, "hessian": hessian, "gradient": gradient, "finite": finite}

    def decide(self, state: _State, evaluation):
        """Keep or reject the trial point (x0 is always kept)."""
        sg, solver, first = lax.stop_gradient, self.solver, state.first
        gain_ratio, actual, predicted = _gain_ratio(
            sg((state.cost, evaluation["cost"], state.step, state.hessian, state.gradient)),
            evaluation["finite"],
        )
        accept, solver_state = solver.update(
            sg(state.solver_state), gain_ratio, evaluation["finite"], actual, sg(state.cost)
        )
        accept = accept | first
        solver_state = _tree_where(first, solver.init(self.n, self.dtype), solver_state)
        point = _tree_where(
            accept,
            (state.x_trial, evaluation["cost"], evaluation["hessian"], evaluation["gradient"]),
            (state.x, state.cost, state.hessian, state.gradient),
        )
        return {
            "point": point,
            "gain_ratio": gain_ratio,
            "actual": actual,
            "predicted": predicted,
            "accept": accept,
            "solver_state": solver_state,
            "iteration": jnp.where(first, state.iteration, state.iteration + 1),
        }

    def test(self, state: _State, evaluation, decision):
        """Stop? (at x0 only on a non-finite start or an exactly zero gradient); the gradient as
        a cosine at the kept point, the step in the solver's scaled variables (see
        `AbstractSolver.scale`)."""
        sg, solver, n = lax.stop_gradient, self.solver, self.n
        termination = self.termination
        function_tolerance = termination.function_tolerance
        parameter_tolerance = termination.parameter_tolerance
        first, accept = state.first, decision["accept"]
        _, cost, hessian, gradient = decision["point"]
        column_norms = jnp.sqrt(jnp.maximum(sg(jnp.diagonal(hessian)), 0.0))
        column_norms = jnp.where(column_norms > 0, column_norms, 1.0)
        residual_norm = jnp.sqrt(2.0 * sg(cost))
        gradient_norm = jnp.max(jnp.abs(sg(gradient)) / column_norms, initial=0.0)
        gradient_norm = jnp.where(residual_norm > 0, gradient_norm / residual_norm, 0.0)
        step_scale = sg(solver.scale(state.solver_state))  # the scaling state.step was made with
        step_norm = jnp.sqrt(jnp.sum((step_scale * sg(state.step)) ** 2))
        x_norm = jnp.sqrt(jnp.sum((step_scale * _parameter_magnitudes(state.x)) ** 2))
        scale_norm = jnp.sqrt(jnp.sum(step_scale**2) / max(n, 1))
        small_step = ~first & (
            step_norm <= parameter_tolerance * (x_norm + parameter_tolerance * scale_norm)
        )
        change = jnp.abs(decision["actual"])
        small_change = ~first & (
            (change < function_tolerance * sg(state.cost))
            | (change < termination.absolute_function_tolerance)
        )
        # a rejected step that promised less than the tolerance: no measurable progress is left
        # (the cost's rounding noise, not the model, decided the rejection)
        small_promise = (
            ~first & ~accept & (decision["predicted"] < function_tolerance * sg(state.cost))
        )
        # at x0 no step has been tried: only an exactly stationary start stops there
        small_gradient = jnp.where(
            first, jnp.all(sg(gradient) == 0), gradient_norm <= termination.gradient_tolerance
        )
        trial_finite = evaluation["finite"]
        converged = (
            (small_step & trial_finite)
            | (small_promise & trial_finite)
            | (accept & (small_change | small_gradient))
        )
        nonfinite = ~trial_finite & (first | small_step | (not solver.rejects_steps))
        solver_state = decision["solver_state"]
        diverged = ~first & solver.diverged(solver_state, sg(cost), sg(state.cost_history[0]))
        if self.verbose:
            jax.debug.callback(
                _print_row,
                state.status == Status.RUNNING,  # stopped problems run on masked under vmap
                first,
                decision["iteration"],
                sg(cost),
                jnp.where(accept & ~first, decision["actual"], 0.0),
                gradient_norm,
                jnp.where(first, 0.0, step_norm),
                jnp.where(first, 0.0, decision["gain_ratio"]),
                solver.damping(solver_state),
                accept,
            )
        # a step that is not finite (`propose`) is NONFINITE too, the status of highest
        # precedence
        status = trust_region.status(
            nonfinite, converged, diverged, decision["iteration"] >= self.max_iterations
        )
        return status, state.cost_history.at[decision["iteration"]].set(sg(cost))

    def relinearize(self, state: _State, evaluation, decision, status):
        """Every trial point was linearized (`evaluate`): the kept point's is at hand."""
        return decision["point"], status

    def propose(self, state: _State, evaluation, decision, cost_history, point, status):
        x, cost, hessian, gradient = point
        step, solver_state = self.solver.step(decision["solver_state"], hessian, gradient)
        step = step.astype(self.dtype)
        finite = _all_finite(lax.stop_gradient(step))
        return _State(
            x=x,
            cost=cost,
            hessian=hessian,
            gradient=gradient,
            solver_state=solver_state,
            x_trial=rplus(x, unflatten_tangents(x, step), self.retraction),
            step=step,
            first=jnp.zeros((), bool),
            iteration=decision["iteration"],
            status=jnp.where(finite, status, Status.NONFINITE).astype(jnp.int32),
            cost_history=cost_history,
        )


# ---- errors --------------------------------------------------------------------------------


def _raise_on_failure(solution: Solution, x0, args, loss) -> Solution:
    """`solution`, after raising the `SolveError` its status calls for: now when the status is
    concrete, when the compiled program runs under `jit` (`lieax._runtime_error.raise_if`), never
    under `vmap` (the statuses are the report)."""
    status = solution.status
    if isinstance(status, jax.core.Tracer):
        return solution._replace(
            status=raise_if(
                status,
                is_failure,
                lambda code: SolveError(
                    f"least_squares ended {Status(code).name} (raised from inside jit; pass "
                    "throw=False to read Solution.status instead)."
                ),
            )
        )
    code = Status(int(np.asarray(status)))
    iterations = int(np.asarray(solution.iterations))
    if code == Status.NONFINITE and iterations == 0:
        inputs = _nonfinite_inputs(x0, args, loss)
        if inputs:
            raise NonFiniteStartError(
                f"least_squares ended NONFINITE at its start: {'; '.join(inputs)}. The "
                "Solution holds x0 unchanged (pass throw=False to get it back)."
            )
    if code == Status.NONFINITE:
        where = "at x0" if iterations == 0 else f"after {iterations} iterations"
        raise SolveError(
            f"least_squares stopped: the residual or its Jacobian is NaN or infinite {where}"
            f"{_describe_cost(solution) if iterations else ''}. Check residual_fn there, or pass "
            "throw=False to get the Solution back."
        )
    if code == Status.DIVERGED:
        raise SolveError(
            f"least_squares diverged after {iterations} iterations{_describe_cost(solution)}: the "
            "cost grew without bound (GaussNewton) or no damping made it decrease "
            "(LevenbergMarquardt). Try LevenbergMarquardt, a better x0 or a robust loss, or pass "
            "throw=False to get the Solution back."
        )
    return solution


def _nonfinite_inputs(x0, args, loss) -> list:
    """What makes a start non-finite, each named by its pytree path: NaN or infinite entries of
    `x0` or `args` (`nonfinite_leaves`), loss scales that are not positive and finite (concrete
    values only)."""
    found = [
        f"{name}{path}{kind} has NaN or infinite entries ({bad} of {size})"
        for name, tree in (("x0", x0), ("args", args))
        for path, kind, bad, size in nonfinite_leaves(tree)
    ]
    is_leaf = lambda node: node is None or isinstance(node, AbstractLoss)  # noqa: E731
    for path, leaf in jax.tree_util.tree_flatten_with_path(loss, is_leaf=is_leaf)[0]:
        if isinstance(leaf, AbstractLoss) and not isinstance(leaf.scale, jax.core.Tracer):
            scale = np.asarray(leaf.scale)
            if not (np.all(np.isfinite(scale)) and np.all(scale > 0)):
                found.append(
                    f"loss{jax.tree_util.keystr(path)} {type(leaf).__name__} has scale {scale}, "
                    "not positive and finite"
                )
    return found


def _describe_cost(solution: Solution) -> str:
    """`' (cost a at the start, b at the end)'` when the costs are concrete (not under `jvp`)."""
    if any(isinstance(a, jax.core.Tracer) for a in (solution.cost, solution.cost_history)):
        return ""
    initial, final = float(np.asarray(solution.cost_history[0])), float(np.asarray(solution.cost))
    return f" (cost {initial:.6e} at the start, {final:.6e} at the last finite iterate)"


# ---- the iteration table -------------------------------------------------------------------

_HEADER = (
    f"{'iter':>5}  {'cost':>13}  {'cost_change':>11}  {'|gradient|':>10}  {'|step|':>10}  "
    f"{'gain_ratio':>10}  {'damping':>10}  accepted"
)


def _print_row(
    active, first, iteration, cost, change, gradient_norm, step_norm, gain_ratio, damping, accepted
):
    if not bool(active):
        return
    if bool(first):
        print(_HEADER)
    print(
        f"{int(iteration):>5d}  {float(cost):>13.6e}  {float(change):>11.2e}  "
        f"{float(gradient_norm):>10.2e}  {float(step_norm):>10.2e}  {float(gain_ratio):>10.2e}  "
        f"{float(damping):>10.2e}  {'yes' if bool(accepted) else 'no'}"
    )


def _print_summary(status, iterations, initial_cost, final_cost):
    print(
        f"{Status(int(status)).name}: {int(iterations)} iterations, "
        f"cost {float(initial_cost):.6e} -> {float(final_cost):.6e}"
    )
