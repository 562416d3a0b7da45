r"""Levenberg-Marquardt on a factor graph, inside one jitted `lax.while_loop`.

Each attempt solves $(H + \lambda D)\,\delta = -g$ with the block normal equations of
`_assembly`, retracts every instance $x \leftarrow x \oplus \delta$ (right perturbation,
`lieax.rplus`, or another `retraction` from `lieax.retractions`) and compares the actual cost
decrease with the decrease predicted by the undamped model,
$-g^\top\delta - \tfrac12 \delta^\top H \delta
= \tfrac12(-g^\top\delta + \lambda\,\delta^\top D\,\delta)$ (the gain ratio, or model fidelity).
$D = I$ (`damping="identity"`, GTSAM's default) or $D = \mathrm{diag}(H)$ clipped to
`[diagonal_min, diagonal_max]` (`damping="marquardt"`, Marquardt 1963, Ceres' default with the
same clipping `[1e-6, 1e32]`): the step then does not depend on the units of the parameters.

$\lambda$ updates (`lambda_update`): `"gtsam"`, GTSAM 4.3's `LevenbergMarquardtOptimizer`
(divide by `lambda_factor` on success, multiply on failure, give up at `lambda_max`; a step is
taken when the fidelity exceeds `min_model_fidelity`); `"nielsen"`, Nielsen's rule as Ceres'
`LevenbergMarquardtStrategy` and `lieax.lstsq.LevenbergMarquardt` (Madsen, Nielsen and
Tingleff, "Methods for non-linear least squares problems", 2004, Sec. 3.2).
`lambda_update="auto"` (`FactorGraph.solve`'s default) takes Nielsen's with the Marquardt
diagonal and GTSAM's with the identity, as Ceres and GTSAM pair them (GTSAM's
`ceresDefaults()`: diagonal damping with `useFixedLambdaFactor=false`, Nielsen's rule). With the
Marquardt diagonal the damping is relative to the curvature of each coordinate, so the $\lambda$
from which steps along weakly determined directions (a point seen over a short baseline, the
free gauge) leave the model's range is a fixed number for the problem; GTSAM's rule, ×10 on
a rejection and ÷10 on any taken step, cannot settle near it: it takes a step at $\lambda$,
fails at $\lambda/10$, takes one at $\lambda$ again, and so on, solving twice per step and
damping up to 10× more than needed (on `lieax.ba.synthetic_bal(3, 7, 18)`, exactly solvable: 19
of 32 solves rejected; Nielsen's, which shrinks $\lambda$ by the gain ratio and grows it by a
doubling factor, 8 of 22, both to a cost of 1e-27).
`algorithm="gauss_newton"` takes every finite step with $\lambda = 0$. These rules (formulas
and sources in `lieax.lstsq._trust_region`), the gain ratio, the precedence of the status codes
and the iteration itself (`lieax.lstsq._iteration.body`: evaluate the trial point, decide, test,
relinearize the kept point, propose the next step) are shared with `lieax.lstsq.least_squares`;
this loop's own are the phases' contents: the block-sparse linear algebra, the one evaluation per
pass and GTSAM's stopping rules, which follow.

An iteration ends with a taken step or, without one, when the cost change is below
`relative_tolerance` × cost; the run stops when an iteration decreases the cost by at most
`absolute_tolerance` or `relative_tolerance` × cost (`CONVERGED`), after `max_iterations`
iterations (`MAX_ITERATIONS`), when $\lambda$ reaches `lambda_max` without a decrease
(`DIVERGED`) or when the linearization is not finite (`NONFINITE`). An exact fit is
`CONVERGED`: `absolute_tolerance` is raised to $\varepsilon c_0$, the rounding error of the
start's cost $c_0$ (a smaller change of the cost is rounding noise, so `absolute_tolerance=0`
stops at the floating-point floor instead of iterating on noise), and running out of damping at
a cost at most $\varepsilon c_0$ is convergence at that floor, not divergence. A point whose gradient is
exactly zero (a zero error, as GTSAM's `errorTol` of 0) is `CONVERGED` (there is no step to try;
at the start, after 0 iterations); no other start is: every other convergence test compares a
tried step's decrease.

What depends on the size of the residual, as in GTSAM: `absolute_tolerance` (GTSAM's
`absoluteErrorTol`) is a cost, absolute by definition (a problem whose whole cost is below it
stops after its first iteration; pass 0 to make every test relative), and $\lambda$ with
`damping="identity"` is in the units of $H$ (`lambda_initial`, `lambda_max`); with
`damping="marquardt"` only the clip of $\mathrm{diag}(H)$ to `diagonal_min` is. The relative
tests (`relative_tolerance`, the predicted decrease against $\varepsilon$ × cost) are
invariant. A non-finite start (values, or data where the factors read them) ends `NONFINITE`
after 0 iterations with the values unchanged.

Each pass of the loop evaluates one trial point (`_assembly.evaluate`: whitened residuals,
Jacobian blocks and weights of every factor kind, in one trace), decides, and when the step is
taken completes the normal equations from that same evaluation (`assemble`, inside a `cond`), as
`lieax.graph.optimize` does: a taken step costs one evaluation, a rejected one an evaluation and
a solve. The first pass evaluates the start itself, so each factor kind is traced and compiled
once (not once for the start and once in the loop; kinds that share a residual function, once
for all of them). XLA CPU's compile time grows with the program's kernels (tens of ms each),
so the loop's finiteness and stationarity tests are floating sums (one kernel each, where a
boolean `all` over an array is three) and the parameters are read inside the loop.
"""

from typing import NamedTuple

import jax
import jax.numpy as jnp
from jax import lax

from .. import _cpu_emitters as cpu_emitters
from ..autodiff._tangents import manifold_leaves, rplus
from ..groups._base import AbstractGroup
from ..lstsq import Status, _iteration
from ..lstsq import _trust_region as trust_region
from ..retractions import exp
from ._assembly import assemble, evaluate
from ._linear import schur_solve, solve_system
from ._variables import flat_tangent_to_tree

PARAMETERS = (
    "lambda_initial",
    "lambda_factor",
    "lambda_max",
    "relative_tolerance",
    "absolute_tolerance",
    "min_model_fidelity",
    "cg_tolerance",
    "max_iterations",
    "diagonal_min",
    "diagonal_max",
)


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
    return treedef.unflatten(
        [
            type(x)._wrap(type(x)._normalize(x._params)) if isinstance(x, AbstractGroup) else x
            for x in leaves
        ]
    )


def retract(variables, values, delta, retraction=exp):
    """Every kind's instances moved by its tangents `delta[k]` `(n_k, d_k)` (by `retraction`, a
    `lieax.retractions.Retraction`)."""
    return tuple(
        _normalized(rplus(v, flat_tangent_to_tree(var, dk), retraction))
        for var, v, dk in zip(variables, values, delta)
    )


def make_loop(graph, options):
    """The jitted `run(values, data, params) -> (values, summary)` of `graph` under the static
    `options` (a dict: method, schur plan, damping, lambda_update, algorithm, retraction,
    history_size, verbose, cg_max_iterations); `summary` is `[cost, lambda, iterations, solves,
    status, *history]`."""
    layout, factors, plans, variables = graph.layout, graph.factors, graph.plans, graph.variables
    method, schur = options["method"], options["schur"]
    marquardt = options["damping"] == "marquardt"
    nielsen = options["lambda_update"] == "nielsen"
    gauss_newton = options["algorithm"] == "gauss_newton"

    def solve(diag, off, rhs, params):
        extra = {
            "cg_tolerance": params["cg_tolerance"],
            "cg_max_iterations": options["cg_max_iterations"],
        }
        if schur is None:
            return solve_system(layout, method, diag, off, rhs, **extra)
        return schur_solve(layout, schur, method, diag, off, rhs, **extra)

    def attempt(values, system, lam, params):
        """One damped solve from `values`: `(trial, predicted decrease, solved)`."""
        diag, off, grad = system
        dtype = lam.dtype
        if marquardt:
            scale = [
                jnp.clip(
                    jnp.diagonal(d, axis1=1, axis2=2),
                    params["diagonal_min"],
                    params["diagonal_max"],
                )
                for d in diag
            ]
        else:
            scale = [jnp.ones(d.shape[:2], dtype) for d in diag]
        damped = tuple(
            d + lam * (s[:, :, None] * jnp.eye(d.shape[-1], dtype=dtype))
            for d, s in zip(diag, scale)
        )
        delta = solve(damped, off, tuple(-g for g in grad), params)
        g_delta = sum(jnp.vdot(g, x) for g, x in zip(grad, delta))
        d_delta = sum(jnp.vdot(s * x, x) for s, x in zip(scale, delta))
        # a NaN or infinite entry of the step makes its scaled square norm NaN or infinite (the
        # scale is positive; so does a step beyond 1e154): one reduction that is computed anyway
        solved = jnp.isfinite(d_delta)
        delta = tuple(jnp.where(solved, x, 0.0) for x in delta)
        predicted = jnp.where(solved, -0.5 * g_delta + 0.5 * lam * d_delta, 0.0)
        return retract(variables, values, delta, options["retraction"]), predicted, solved

    def assembled(parts, dtype):
        """The normal equations from `evaluate`'s parts, and whether they are finite: a NaN or
        infinite entry anywhere makes the sum of the diagonal blocks and gradients NaN or
        infinite (a coupling block's entries come from the same Jacobian columns as two
        diagonal blocks'; so does an overflowing sum). One floating sum per array is one small
        kernel, where XLA CPU splits a boolean `all` into three."""
        system = jax.tree_util.tree_map(lambda a: a.astype(dtype), assemble(layout, plans, parts))
        diag, _, grad = system
        return system, jnp.isfinite(sum(jnp.sum(a) for a in (*diag, *grad)))

    def named(vector):
        return dict(zip(PARAMETERS, vector))

    def loop(values, data, vector):
        max_iterations = named(vector)["max_iterations"].astype(jnp.int32)
        dtype = vector.dtype
        zero = jnp.zeros((), jnp.int32)
        lam0 = jnp.zeros((), dtype) if gauss_newton else named(vector)["lambda_initial"]
        nu0 = jnp.asarray(2.0, dtype)
        nan = jnp.asarray(jnp.nan, dtype)
        # the first pass of `body` evaluates the start itself (`started` False), so that every
        # factor kind is traced and compiled once
        system = (
            tuple(jnp.zeros((n, d, d), dtype) for n, d in zip(layout.counts, layout.dims)),
            tuple(
                jnp.zeros((len(layout.pairs[k][0]), layout.dims[k[0]], layout.dims[k[1]]), dtype)
                for k in layout.pairs
            ),
            tuple(jnp.zeros((n, d), dtype) for n, d in zip(layout.counts, layout.dims)),
        )
        history = jnp.full((options["history_size"],), jnp.nan, dtype)
        running = jnp.asarray(Status.RUNNING, jnp.int32)
        false = jnp.zeros((), bool)
        state = _State(values, values, nan, nan, false, system, lam0, nu0, zero, zero, running,
                       history, false)  # fmt: skip

        def evaluate_trial(state):
            # the parameters are read inside the loop, where XLA fuses each read into its use
            # (read before it, each would be a kernel of its own)
            params = named(vector)
            new_cost, parts = evaluate(factors, plans, state.trial, data)
            return params, new_cost, parts

        def decide(state, evaluation):
            cost, predicted, lam, nu, started = (
                state.cost, state.predicted, state.lam, state.nu, state.started
            )  # fmt: skip
            params, new_cost, _ = evaluation
            change = cost - new_cost
            valid = state.solved & (predicted >= 0) & jnp.isfinite(new_cost)
            fidelity = trust_region.gain_ratio(change, predicted)
            if gauss_newton:
                success = state.solved & jnp.isfinite(new_cost)
                stop_search = jnp.zeros((), bool)
                gave_up = ~success
                new_lam, new_nu = lam, nu
            else:
                success = (
                    valid
                    & (predicted > jnp.finfo(dtype).eps * cost)
                    & trust_region.accepts(fidelity, params["min_model_fidelity"], inclusive=False)
                )
                stop_search = (
                    valid & ~success & (jnp.abs(change) < params["relative_tolerance"] * cost)
                )
                if nielsen:
                    new_lam, new_nu = trust_region.nielsen(success, fidelity, lam, nu)
                else:
                    new_lam = trust_region.gtsam(success, lam, params["lambda_factor"])
                    new_nu = nu
                gave_up = (
                    ~success
                    & ~stop_search
                    & trust_region.damping_exhausted(new_lam, params["lambda_max"], inclusive=True)
                )
            # the start is taken as it is
            success = jnp.where(started, success, jnp.isfinite(new_cost))
            gave_up = gave_up & started
            done = started & (success | stop_search | gave_up)
            iterations = state.iterations + done.astype(jnp.int32)
            next_cost = jnp.where(success | ~started, new_cost, cost)
            return _Decision(
                fidelity, success, gave_up, done, iterations, next_cost, new_lam, new_nu
            )

        def test(state, evaluation, decision):
            cost, started = state.cost, state.started
            done, gave_up, iterations, next_cost = (
                decision.done, decision.gave_up, decision.iterations, decision.next_cost
            )  # fmt: skip
            params, new_cost, _ = evaluation
            decrease = cost - next_cost
            # the rounding error of the start's cost: a smaller change is noise, and a cost below
            # it is an exact fit at the floating-point floor (`history[0]` is the start's cost)
            floor = jnp.finfo(dtype).eps * state.history[0]
            converged = (
                done
                & ~gave_up
                & (
                    (jnp.abs(decrease) <= jnp.maximum(params["absolute_tolerance"], floor))
                    | (jnp.abs(decrease) <= params["relative_tolerance"] * cost)
                )
            ) | (gave_up & (next_cost <= floor))
            # no step decreased the cost: Levenberg-Marquardt ran out of damping, Gauss-Newton's
            # step was not finite
            nonfinite, diverged = ~jnp.isfinite(next_cost), gave_up & (decrease <= 0)
            if gauss_newton:
                nonfinite, diverged = nonfinite | diverged, False
            status = trust_region.status(
                nonfinite,
                converged,
                diverged,
                (done | ~started) & (iterations >= max_iterations),
            )
            history = state.history
            history = jnp.where(done | ~started, history.at[iterations].set(next_cost), history)
            if options["verbose"]:
                lax.cond(
                    started,
                    lambda: jax.debug.print(
                        "iteration {it:3d}  cost {c:.10g} -> {nc:.10g}  gain ratio {f:.3f}  "
                        "lambda {l:.1e}  accepted {ok}",
                        it=iterations, c=cost, nc=new_cost, f=decision.fidelity, l=state.lam,
                        ok=decision.success,
                    ),
                    lambda: None,
                )  # fmt: skip
            return status, history

        # a taken step's evaluation is the first half of its linearization
        def relinearize(state, evaluation, decision, status):
            success, started = decision.success, state.started
            values = jax.tree_util.tree_map(
                lambda a, b: jnp.where(success, a, b), state.trial, state.values
            )
            lam = jnp.where(~started | (decision.done & ~success), state.lam, decision.lam)
            nu = jnp.where(started, decision.nu, state.nu)
            system, finite = lax.cond(
                success & (status == Status.RUNNING),
                lambda: assembled(evaluation[2], dtype),
                lambda: (state.system, jnp.ones((), bool)),
            )
            status = jnp.where(finite, status, Status.NONFINITE).astype(jnp.int32)
            # a point with an exactly zero gradient (a zero error: GTSAM's `errorTol` = 0) is
            # stationary: no step to try (at the start: converged after 0 iterations)
            stationary = sum(jnp.sum(jnp.abs(g)) for g in system[2]) == 0
            status = jnp.where(
                (status == Status.RUNNING) & stationary, Status.CONVERGED, status
            ).astype(jnp.int32)
            return (values, system, lam, nu), status

        def propose(state, evaluation, decision, history, point, status):
            values, system, lam, nu = point
            go_on = status == Status.RUNNING
            trial, predicted, solved = lax.cond(
                go_on,
                lambda: attempt(values, system, lam, evaluation[0]),
                lambda: (values, jnp.zeros((), dtype), jnp.zeros((), bool)),
            )
            return _State(
                values, trial, decision.next_cost, predicted, solved, system, lam, nu,
                decision.iterations, state.solves + go_on.astype(jnp.int32), status, history,
                jnp.ones((), bool),
            )  # fmt: skip

        body = _iteration.body(evaluate_trial, decide, test, relinearize, propose)

        state = lax.while_loop(lambda s: s.status == Status.RUNNING, body, state)
        values, _, cost, _, _, _, lam, _, iterations, solves, status, history, _ = state
        scalars = jnp.stack([cost, lam, *(a.astype(dtype) for a in (iterations, solves, status))])
        return values, jnp.concatenate([scalars, history])

    return cpu_emitters.jit(loop)
