r"""The iteration of Levenberg-Marquardt and Gauss-Newton, once for the two loops of the library:
`least_squares` (dense normal equations, `_least_squares`) and the factor-graph loop
(block-sparse normal equations, `lieax.factorgraph._solve`). `body` is the `lax.while_loop`
body of both; each loop supplies its five phases, called in this order:

1. `evaluate(state)`: the trial point $x \oplus \delta$ that the previous pass proposed (the
   first pass: the start) evaluated, its cost and as much of its linearization as the loop
   computes at every trial point;
2. `decide(state, evaluation)`: the gain ratio
   $\varrho = (c(x) - c(x \oplus \delta)) / (m(0) - m(\delta))$, whether the trial point is
   kept, the next damping (the rules of `_trust_region`);
3. `test(state, evaluation, decision)`: the loop's stopping rules, a `Status` code
   (`_trust_region.status`), and the loop's record of the pass (its cost history); returns
   `(status, record)`;
4. `relinearize(state, evaluation, decision, status)`: the kept point and its normal equations
   $H = J^\top W J$, $g = J^\top W r$, and the status once they are known (not finite,
   stationary); returns `(point, status)`;
5. `propose(state, evaluation, decision, record, point, status)`: the step $\delta$ from the
   damped normal equations $(H + \mu D)\,\delta = -g$ at the kept point, and the next state.

What the phases do is each loop's own where the loops differ in substance: the linear algebra
(dense or block-sparse), how much of a linearization a trial point gets (`least_squares`
linearizes every trial point, so the kept point's normal equations are at hand; the factor graph
evaluates residuals and Jacobian blocks at every trial point and assembles the normal equations
only for a kept one, inside a `cond`) and the stopping tests each runs of the one
`Termination` (MINPACK-style scaled tests counting every trial point; GTSAM's cost-change tests
counting outer iterations). The body adds no operation of its own:
a loop's compiled program is its phases' in sequence. `run` is the one loop that runs a body.
"""

import jax
import jax.numpy as jnp
from jax import lax

from ._solution import Status


def run(phases, initial, unrolled_length=None):
    """The loop of lieax's Levenberg-Marquardt and Gauss-Newton: `body` of `phases` (an object
    with the five phases as methods: `_least_squares._DensePhases`, the factor graph's
    `_solve._Phases`) from the state `initial` until its `status` is no longer `RUNNING`: a
    `lax.while_loop`, or with `unrolled_length` a `lax.scan` of that many iterations masked
    once stopped, so that reverse mode can go through them (every problem of a `vmap` runs in
    lockstep either way; a stopped one keeps its state)."""
    step = body(phases.evaluate, phases.decide, phases.test, phases.relinearize, phases.propose)

    def running(state):
        return state.status == Status.RUNNING

    if unrolled_length is None:
        return lax.while_loop(running, step, initial)

    def masked(state, _):
        new = step(state)
        return jax.tree_util.tree_map(
            lambda a, b: jnp.where(running(state), a, b), new, state
        ), None

    return lax.scan(masked, initial, None, length=unrolled_length)[0]


def body(evaluate, decide, test, relinearize, propose):
    """The `lax.while_loop` body `state -> state` of the five phases (see the module
    docstring)."""

    def iteration(state):
        evaluation = evaluate(state)
        decision = decide(state, evaluation)
        status, record = test(state, evaluation, decision)
        point, status = relinearize(state, evaluation, decision, status)
        return propose(state, evaluation, decision, record, point, status)

    return iteration
