"""What `FactorGraph.solve` returns."""

from typing import NamedTuple

import jax

from ..lstsq._solution import SolverResult


class _SolveResultFields(NamedTuple):
    values: tuple
    cost: jax.Array
    iterations: jax.Array
    linear_solves: jax.Array
    status: jax.Array
    cost_history: jax.Array
    lambda_: jax.Array


class SolveResult(SolverResult, _SolveResultFields):
    r"""The result of `FactorGraph.solve`, a pytree (so it batches under `vmap`); a
    `lieax.lstsq.SolverResult`.

    **Fields:**

    - `values`: the solution, a tuple in the order of the graph's `variables`.
    - `cost`: $\tfrac12 \sum \rho(\|R r\|^2)$ at `values`.
    - `iterations`: outer iterations (linearizations), as GTSAM counts them.
    - `linear_solves`: linear solves, rejected steps included.
    - `status`: an integer `lieax.lstsq.Status` code; `status_name` reads it.
    - `cost_history`: the initial cost, then the cost after each iteration; NaN after the last.
    - `lambda_`: the damping at the end.
    """

    __slots__ = ()
    _repr_fields = ("cost", "iterations", "linear_solves", "lambda_")
