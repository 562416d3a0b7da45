r"""Levenberg-Marquardt on a factor graph, inside one jitted `lax.while_loop`: the block-sparse
backend of lieax's Levenberg-Marquardt, whose options are `lieax.lstsq.LevenbergMarquardt` (or
`GaussNewton`), the options object of `lieax.lstsq.least_squares` too.

Each attempt solves $(H + \mu D)\,\delta = -g$ with the block normal equations of
`_assembly`, retracts every instance $x \leftarrow x \oplus \delta$ (right perturbation,
`lieax.rplus`, or another `retraction` from `lieax.retractions`) and compares the actual cost
decrease with the decrease predicted by the undamped model,
$-g^\top\delta - \tfrac12 \delta^\top H \delta
= \tfrac12(-g^\top\delta + \mu\,\delta^\top D\,\delta)$ (the gain ratio, or model fidelity).
The options' `scaling` gives $D$: `"identity"`, $D = I$ (GTSAM's default, the preset
`LevenbergMarquardt.gtsam()`); `"clipped"`, $D = \mathrm{diag}(H)$ clipped to
`[min_diagonal, max_diagonal]` (Marquardt 1963, GTSAM's `diagonalDamping`): the step then does
not depend on the units of the parameters; `"jacobi"`, Ceres' `jacobi_scaling`: the clip applies
to the Jacobi-scaled diagonal, $D = (1 + c)^2\,\mathrm{clip}(\mathrm{diag}(H) / (1 + c)^2)$,
$c = \sqrt{\mathrm{diag}(H)}$ (the step of `least_squares`' `"jacobi"` in exact arithmetic).

$\mu$ updates (`damping_update`): `"gtsam"`, GTSAM 4.3's `LevenbergMarquardtOptimizer`
(divide by `damping_factor` on success, multiply on failure, give up at `max_damping`; a step is
taken when the fidelity exceeds `min_gain_ratio`); `"nielsen"`, Nielsen's rule as Ceres'
`LevenbergMarquardtStrategy` and `least_squares`' default (Madsen, Nielsen and Tingleff,
"Methods for non-linear least squares problems", 2004, Sec. 3.2). $\mu$ is kept at least
`min_damping`. With the Marquardt diagonal the damping is relative to the curvature of each
coordinate, so the $\mu$ from which steps along weakly determined directions (a point seen over
a short baseline, the free gauge) leave the model's range is a fixed number for the problem;
GTSAM's rule, ×10 on a rejection and ÷10 on any taken step, cannot settle near it: it takes a
step at $\mu$, fails at $\mu/10$, takes one at $\mu$ again, and so on, solving twice per step
and damping up to 10× more than needed (on `lieax.ba.synthetic_bal(3, 7, 18)`, exactly
solvable: 19 of 32 solves rejected; Nielsen's, which shrinks $\mu$ by the gain ratio and grows
it by a doubling factor, 8 of 22, both to a cost of 1e-27): pair the diagonal with
`damping_update="nielsen"`. `GaussNewton()` takes every finite step with $\mu = 0$, and stops
`DIVERGED` when the cost exceeds its `divergence_factor` times the start's. These
rules (formulas and sources in `lieax.lstsq._trust_region`), the gain ratio, the precedence of
the status codes and the iteration itself (`lieax.lstsq._iteration.body`: evaluate the trial
point, decide, test, relinearize the kept point, propose the next step) are shared with
`lieax.lstsq.least_squares`; this loop's own are the phases' contents (`_Phases`): the
block-sparse linear algebra, the one evaluation per pass and GTSAM's stopping rules, which follow.

When the loop stops is `lieax.lstsq.Termination` (default `Termination.gtsam()`), with
`counting="outer"`: an iteration ends with a taken step or, without one, when the cost change is
below `function_tolerance` × cost; the run stops when an iteration decreases the cost by at most
`absolute_function_tolerance` or `function_tolerance` × cost (`CONVERGED`; GTSAM's
`absoluteErrorTol` and `relativeErrorTol`), after `max_iterations` iterations
(`MAX_ITERATIONS`), when $\mu$ reaches `max_damping` without a decrease (`DIVERGED`) or when
the linearization is not finite (`NONFINITE`). An exact fit is `CONVERGED`:
`absolute_function_tolerance` is raised to $\varepsilon c_0$, the rounding error of the start's
cost $c_0$ (a smaller change of the cost is rounding noise, so `absolute_function_tolerance=0`
stops at the floating-point floor instead of iterating on noise), and running out of damping at
a cost at most $\varepsilon c_0$ is convergence at that floor, not divergence. A point whose
gradient is exactly zero (a zero error, as GTSAM's `errorTol` of 0) is `CONVERGED` (there is no
step to try; at the start, after 0 iterations); no other start is: every other convergence test
compares a tried step's decrease. GTSAM has no gradient or step test, and neither has this loop
(`Termination.gradient_tolerance` and `parameter_tolerance` must be 0).

What depends on the size of the residual, as in GTSAM: `absolute_function_tolerance` is a cost,
absolute by definition (a problem whose whole cost is below it stops after its first iteration;
pass 0 to make every test relative), and $\mu$ with `scaling="identity"` is in the units of $H$
(`initial_damping`, `max_damping`); with the diagonal scalings only the clip of
$\mathrm{diag}(H)$ to `min_diagonal` is. The relative tests (`function_tolerance`, the predicted
decrease against $\varepsilon$ × cost) are invariant. A non-finite start (values, or data where
the factors read them) ends `NONFINITE` after 0 iterations with the values unchanged.

Each pass of the loop evaluates one trial point (`_assembly.evaluate`: whitened residuals,
Jacobian blocks and weights of every factor kind, in one trace), decides, and when the step is
taken completes the normal equations from that same evaluation (`assemble`, inside a `cond`): a
taken step costs one evaluation, a rejected one an evaluation and a solve. The first pass
evaluates the start itself, so each factor kind is traced and compiled once (not once for the
start and once in the loop; kinds that share a residual function, once for all of them). XLA
CPU's compile time grows with the program's kernels (tens of ms each), so the loop's finiteness
and stationarity tests are floating sums (one kernel each, where a boolean `all` over an array
is three) and the parameters are read inside the loop.
"""

from typing import NamedTuple

import jax
import jax.numpy as jnp
from jax import lax

from .. import _cpu_emitters as cpu_emitters
from ..autodiff._tangents import manifold_leaves, rplus
from ..groups import AbstractGroup
from ..lstsq import GaussNewton, LevenbergMarquardt, Status, _iteration
from ..lstsq import _trust_region as trust_region
from ..retractions import exp
from ._assembly import assemble, evaluate
from ._fingerprint import loop_fingerprint
from ._linear import schur_solve, solve_system
from ._variables import flat_tangent_to_tree

# the numeric options, an array argument of the compiled loop (so that new values reuse it)
PARAMETERS = (
    "initial_damping",
    "damping_factor",
    "min_damping",
    "max_damping",
    "min_gain_ratio",
    "min_diagonal",
    "max_diagonal",
    "divergence_factor",
    "function_tolerance",
    "absolute_function_tolerance",
    "cg_tolerance",
    "max_iterations",
)
SCALINGS = ("identity", "clipped", "jacobi")
DAMPING_UPDATES = ("gtsam", "nielsen")


def static_options(solver):
    """`(gauss_newton, scaling, damping_update, floor, inclusive_gain_ratio,
    inclusive_max_damping)`: what of `solver` (a `LevenbergMarquardt` or `GaussNewton`) shapes
    the compiled loop (`floor`: whether the damping has a positive lower bound to keep,
    `min_damping`), checked against what this backend supports (a `ValueError` names the
    option it cannot honour)."""
    if isinstance(solver, GaussNewton):
        return True, "identity", "gtsam", False, False, True
    if not isinstance(solver, LevenbergMarquardt):
        raise TypeError(
            "solver must be a lieax.lstsq.LevenbergMarquardt (e.g. LevenbergMarquardt.gtsam(), "
            f"the default) or lieax.lstsq.GaussNewton(), got {solver!r} (the linear solver is "
            "linear_solver=)."
        )
    if solver.scaling not in SCALINGS:
        raise ValueError(
            f"FactorGraph.solve supports the scalings {SCALINGS} (LevenbergMarquardt.scaling), "
            f"got {solver.scaling!r} (its running column norms are least_squares' only)."
        )
    if solver.damping_update not in DAMPING_UPDATES:
        raise ValueError(
            f"FactorGraph.solve supports the damping updates {DAMPING_UPDATES} "
            f"(LevenbergMarquardt.damping_update), got {solver.damping_update!r} (MINPACK's radius "
            "needs least_squares' dense solves)."
        )
    return (
        False,
        solver.scaling,
        solver.damping_update,
        bool(solver.min_damping > 0),
        solver.inclusive_gain_ratio,
        solver.inclusive_max_damping,
    )


def numeric_options(solver, termination, cg_tolerance):
    """The values of `PARAMETERS`: `solver`'s constants (the damping's of a `LevenbergMarquardt`,
    the divergence factor of a `GaussNewton`; each loop reads its own), the tolerances and the
    iteration limit of `termination` (a `Termination`) and `cg_tolerance`."""
    constants = {name: getattr(solver, name, 0.0) for name in PARAMETERS[:8]}
    stopping = {name: getattr(termination, name) for name in PARAMETERS[8:10]}
    return {**constants, **stopping, "cg_tolerance": cg_tolerance,
            "max_iterations": termination.max_iterations}  # fmt: skip


class _State(NamedTuple):
    """The loop's state: the kept values, the trial point proposed from them with its predicted
    decrease (and whether its solve was finite), the normal equations at the kept values, the
    damping (Nielsen's factor `nu`), counters, status and cost history; `started` is False
    until the first pass has evaluated the start."""

    values: tuple
    trial: tuple
    cost: jax.Array
    predicted: jax.Array
    solved: jax.Array
    system: tuple
    lam: jax.Array
    nu: jax.Array
    iterations: jax.Array
    solves: jax.Array
    status: jax.Array
    history: jax.Array
    started: jax.Array


class _Decision(NamedTuple):
    """A pass's decisions: the gain ratio, whether the trial point is taken, whether the damping
    is exhausted, whether the iteration is done, the iteration count, the cost kept, and the
    damping rule's next `lam` and `nu`."""

    fidelity: jax.Array
    success: jax.Array
    gave_up: jax.Array
    done: jax.Array
    iterations: jax.Array
    next_cost: jax.Array
    lam: jax.Array
    nu: jax.Array


def _normalized(tree):
    leaves, treedef = manifold_leaves(tree, "value")
    return treedef.unflatten([x.normalize() if isinstance(x, AbstractGroup) else x for x in leaves])


def retract(variables, values, delta, retraction=exp):
    """Every kind's instances moved by its tangents `delta[k]` `(n_k, d_k)` (by `retraction`, a
    `lieax.retractions.Retraction`)."""
    return tuple(
        _normalized(rplus(v, flat_tangent_to_tree(var, dk), retraction))
        for var, v, dk in zip(variables, values, delta)
    )


def _damping_diagonal(scaling, block, params):
    """$D$'s diagonal `(n, d)` for the diagonal blocks `block` `(n, d, d)` of $H$ (see the module
    docstring)."""
    if scaling == "identity":
        return jnp.ones(block.shape[:2], block.dtype)
    h = jnp.diagonal(block, axis1=1, axis2=2)
    if scaling == "clipped":
        return jnp.clip(h, params["min_diagonal"], params["max_diagonal"])
    squared = (1.0 + jnp.sqrt(jnp.maximum(lax.stop_gradient(h), 0.0))) ** 2
    return squared * jnp.clip(h / squared, params["min_diagonal"], params["max_diagonal"])


def make_loop(graph, options, ready=None):
    """The jitted `run(values, data, params) -> (values, summary, system)` of `graph` under the
    static `options` (a dict: method, schur plan, scaling, damping_update, gauss_newton, floor,
    retraction, history_size, verbose, cg_max_iterations); `params` is the array of `PARAMETERS`;
    `summary` is `[cost, damping, iterations, solves, status, *history]`; `system` the undamped
    normal equations `(diag, off, grad)` at the returned values, per kind of `graph.layout`
    (with a `max_iterations` of 0, the linearization of the start: what
    `lieax.factorgraph.marginal_covariances` reads, with no program of its own). For a bucketed
    graph `graph` is its `_buckets.Buckets`, and `run` takes the structure as a fourth operand
    (`Buckets.operands`), so that every graph of its buckets calls the one program. `ready()`,
    where given, is called before a loop loaded from `lieax._executable_store` first runs (what
    its trace would have waited for: the Cholesky plan's registration)."""

    def loop(values, data, vector, *structure):
        view = graph.traced(*structure) if structure else graph
        phases = _Phases(view, options, data, vector)
        state = _iteration.run(phases, phases.initial_state(values))
        values, _, cost, _, _, system, lam, _, iterations, solves, status, history, _ = state
        dtype = vector.dtype
        scalars = jnp.stack([cost, lam, *(a.astype(dtype) for a in (iterations, solves, status))])
        return values, jnp.concatenate([scalars, history]), system

    def fingerprint():
        return loop_fingerprint(graph, options)

    return cpu_emitters.jit(
        loop, options=cpu_emitters.SOLVER_LOOP_OPTIONS, fingerprint=fingerprint, before_run=ready
    )


class _Phases:
    """The five phases of `_iteration.body` for one trace of the loop: the graph's structure,
    the static `options`, the factor `data` and the `vector` of numeric options (read inside the
    loop, where XLA fuses each read into its use: read before it, each would be a kernel of its
    own)."""

    def __init__(self, graph, options, data, vector):
        self.layout, self.factors, self.plans = graph.layout, graph.factors, graph.plans
        self.variables, self.options = graph.variables, options
        self.data, self.vector = data, vector
        self.dtype = vector.dtype
        self.gauss_newton = options["gauss_newton"]
        # read once, outside the loop (a read inside would be a kernel of every pass)
        self.max_iterations = self.params()["max_iterations"].astype(jnp.int32)

    def params(self):
        return dict(zip(PARAMETERS, self.vector))

    def initial_state(self, values):
        """The state before the first pass, which evaluates the start itself (`started` False),
        so that every factor kind is traced and compiled once."""
        layout, dtype = self.layout, self.dtype
        zero = jnp.zeros((), jnp.int32)
        lam0 = jnp.zeros((), dtype) if self.gauss_newton else self.params()["initial_damping"]
        nan = jnp.asarray(jnp.nan, dtype)
        system = (
            tuple(jnp.zeros((n, d, d), dtype) for n, d in zip(layout.counts, layout.dims)),
            tuple(
                jnp.zeros((len(layout.pairs[k][0]), layout.dims[k[0]], layout.dims[k[1]]), dtype)
                for k in layout.pairs
            ),
            tuple(jnp.zeros((n, d), dtype) for n, d in zip(layout.counts, layout.dims)),
        )
        history = jnp.full((self.options["history_size"],), jnp.nan, dtype)
        running = jnp.asarray(Status.RUNNING, jnp.int32)
        false = jnp.zeros((), bool)
        return _State(values, values, nan, nan, false, system, lam0, jnp.asarray(2.0, dtype),
                      zero, zero, running, history, false)  # fmt: skip

    def evaluate(self, state):
        new_cost, parts = evaluate(self.factors, self.plans, state.trial, self.data)
        return self.params(), new_cost, parts

    def decide(self, state, evaluation):
        cost, predicted, lam, nu, started = (
            state.cost, state.predicted, state.lam, state.nu, state.started
        )  # fmt: skip
        params, new_cost, _ = evaluation
        change = cost - new_cost
        valid = state.solved & (predicted >= 0) & jnp.isfinite(new_cost)
        fidelity = trust_region.gain_ratio(change, predicted)
        if self.gauss_newton:
            success = state.solved & jnp.isfinite(new_cost)
            stop_search = jnp.zeros((), bool)
            gave_up = ~success
            new_lam, new_nu = lam, nu
        else:
            success = (
                valid
                & (predicted > jnp.finfo(self.dtype).eps * cost)
                & trust_region.accepts(
                    fidelity, params["min_gain_ratio"],
                    inclusive=self.options["inclusive_gain_ratio"],
                )
            )  # fmt: skip
            stop_search = valid & ~success & (jnp.abs(change) < params["function_tolerance"] * cost)
            if self.options["damping_update"] == "nielsen":
                new_lam, new_nu = trust_region.nielsen(success, fidelity, lam, nu)
            else:
                new_lam = trust_region.gtsam(success, lam, params["damping_factor"])
                new_nu = nu
            if self.options["floor"]:  # a zero floor (GTSAM's) adds no operation to the loop
                new_lam = jnp.maximum(new_lam, params["min_damping"])
            gave_up = (
                ~success
                & ~stop_search
                & trust_region.damping_exhausted(
                    new_lam, params["max_damping"], inclusive=self.options["inclusive_max_damping"]
                )
            )
        # the start is taken as it is
        success = jnp.where(started, success, jnp.isfinite(new_cost))
        gave_up = gave_up & started
        done = started & (success | stop_search | gave_up)
        iterations = state.iterations + done.astype(jnp.int32)
        next_cost = jnp.where(success | ~started, new_cost, cost)
        return _Decision(fidelity, success, gave_up, done, iterations, next_cost, new_lam, new_nu)

    def test(self, state, evaluation, decision):
        cost, started = state.cost, state.started
        done, gave_up, iterations, next_cost = (
            decision.done, decision.gave_up, decision.iterations, decision.next_cost
        )  # fmt: skip
        params, new_cost, _ = evaluation
        decrease = cost - next_cost
        # the rounding error of the start's cost: a smaller change is noise, and a cost below
        # it is an exact fit at the floating-point floor (`history[0]` is the start's cost)
        floor = jnp.finfo(self.dtype).eps * state.history[0]
        converged = (
            done
            & ~gave_up
            & (
                (jnp.abs(decrease) <= jnp.maximum(params["absolute_function_tolerance"], floor))
                | (jnp.abs(decrease) <= params["function_tolerance"] * cost)
            )
        ) | (gave_up & (next_cost <= floor))
        # no step decreased the cost: Levenberg-Marquardt ran out of damping, Gauss-Newton's
        # step was not finite
        nonfinite, diverged = ~jnp.isfinite(next_cost), gave_up & (decrease <= 0)
        if (
            self.gauss_newton
        ):  # its divergence: the cost grew past `divergence_factor` x the start's
            nonfinite = nonfinite | diverged
            diverged = trust_region.cost_diverged(
                next_cost, state.history[0], params["divergence_factor"]
            )
        status = trust_region.status(
            nonfinite, converged, diverged, (done | ~started) & (iterations >= self.max_iterations)
        )
        history = state.history
        history = jnp.where(done | ~started, history.at[iterations].set(next_cost), history)
        if self.options["verbose"]:
            lax.cond(
                started,
                lambda: jax.debug.print(
                    "iteration {it:3d}  cost {c:.10g} -> {nc:.10g}  gain ratio {f:.3f}  "
                    "damping {l:.1e}  accepted {ok}",
                    it=iterations, c=cost, nc=new_cost, f=decision.fidelity, l=state.lam,
                    ok=decision.success,
                ),
                lambda: None,
            )  # fmt: skip
        return status, history

    def relinearize(self, state, evaluation, decision, status):
        """The kept point; a taken step's evaluation is the first half of its linearization."""
        success, started = decision.success, state.started
        values = jax.tree_util.tree_map(
            lambda a, b: jnp.where(success, a, b), state.trial, state.values
        )
        lam = jnp.where(~started | (decision.done & ~success), state.lam, decision.lam)
        nu = jnp.where(started, decision.nu, state.nu)
        # a taken step is assembled even when it ends the solve, so that `system` is the one at
        # the returned values (a solve that stops on it is not made NONFINITE by it)
        system, finite = lax.cond(
            success,
            lambda: self.assembled(evaluation[2]),
            lambda: (state.system, jnp.ones((), bool)),
        )
        status = jnp.where(finite | (status != Status.RUNNING), status, Status.NONFINITE)
        status = status.astype(jnp.int32)
        # a point with an exactly zero gradient (a zero error: GTSAM's `errorTol` = 0) is
        # stationary: no step to try (at the start: converged after 0 iterations)
        stationary = sum(jnp.sum(jnp.abs(g)) for g in system[2]) == 0
        status = jnp.where(
            (status == Status.RUNNING) & stationary, Status.CONVERGED, status
        ).astype(jnp.int32)
        return (values, system, lam, nu), status

    def propose(self, state, evaluation, decision, history, point, status):
        values, system, lam, nu = point
        go_on = status == Status.RUNNING
        trial, predicted, solved = lax.cond(
            go_on,
            lambda: self.attempt(values, system, lam, evaluation[0]),
            lambda: (values, jnp.zeros((), self.dtype), jnp.zeros((), bool)),
        )
        return _State(
            values, trial, decision.next_cost, predicted, solved, system, lam, nu,
            decision.iterations, state.solves + go_on.astype(jnp.int32), status, history,
            jnp.ones((), bool),
        )  # fmt: skip

    def assembled(self, parts):
        """The normal equations from `evaluate`'s parts, and whether they are finite: a NaN or
        infinite entry anywhere makes the sum of the diagonal blocks and gradients NaN or
        infinite (a coupling block's entries come from the same Jacobian columns as two
        diagonal blocks'; so does an overflowing sum). One floating sum per array is one small
        kernel, where XLA CPU splits a boolean `all` into three."""
        system = assemble(self.layout, self.plans, parts)
        system = jax.tree_util.tree_map(lambda a: a.astype(self.dtype), system)
        diag, _, grad = system
        return system, jnp.isfinite(sum(jnp.sum(a) for a in (*diag, *grad)))

    def attempt(self, values, system, lam, params):
        """One damped solve from `values`: `(trial, predicted decrease, solved)`."""
        diag, off, grad = system
        scale = [_damping_diagonal(self.options["scaling"], d, params) for d in diag]
        damped = tuple(
            d + lam * (s[:, :, None] * jnp.eye(d.shape[-1], dtype=self.dtype))
            for d, s in zip(diag, scale)
        )
        delta = self.solve(damped, off, tuple(-g for g in grad), params)
        g_delta = sum(jnp.vdot(g, x) for g, x in zip(grad, delta))
        d_delta = sum(jnp.vdot(s * x, x) for s, x in zip(scale, delta))
        # a NaN or infinite entry of the step makes its scaled square norm NaN or infinite (the
        # scale is positive; so does a step beyond 1e154): one reduction that is computed anyway
        solved = jnp.isfinite(d_delta)
        delta = tuple(jnp.where(solved, x, 0.0) for x in delta)
        predicted = jnp.where(solved, -0.5 * g_delta + 0.5 * lam * d_delta, 0.0)
        trial = retract(self.variables, values, delta, self.options["retraction"])
        return trial, predicted, solved

    def solve(self, diag, off, rhs, params):
        """The linear solve of the damped system (`_linear`: the layout's method, with the Schur
        complement when the options eliminate a kind)."""
        options = self.options
        extra = {
            "cg_tolerance": params["cg_tolerance"],
            "cg_max_iterations": options["cg_max_iterations"],
        }
        if options["schur"] is None:
            return solve_system(self.layout, options["method"], diag, off, rhs, **extra)
        return schur_solve(
            self.layout, options["schur"], options["method"], diag, off, rhs, **extra
        )
