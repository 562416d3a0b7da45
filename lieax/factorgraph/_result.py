"""What `FactorGraph.solve` returns."""

from typing import NamedTuple

import jax
import numpy as np

from ..lstsq import Status
from ..lstsq._solution import status_names


class SolveResult(NamedTuple):
    r"""The result of `FactorGraph.solve`, a pytree (so it batches under `vmap`).

    **Fields:**
    - `values`: the solution, a tuple in the order of the graph's `variables`.
    - `cost`: $\tfrac12 \sum \rho(\|R r\|^2)$ at `values`.
    - `iterations`: outer iterations (linearizations), as GTSAM counts them.
    - `linear_solves`: linear solves, rejected steps included.
    - `status`: an integer `lieax.lstsq.Status` code; `status_name` reads it.
    - `cost_history`: the initial cost, then the cost after each iteration; NaN after the last.
    - `lambda_`: the damping at the end.
    """

    values: tuple
    cost: jax.Array
    iterations: jax.Array
    linear_solves: jax.Array
    status: jax.Array
    cost_history: jax.Array
    lambda_: jax.Array

    @property
    def status_name(self):
        """The `Status` name, or an array of names for a batch (outside `jit`)."""
        return status_names(self.status)

    @property
    def converged(self) -> jax.Array:
        return self.status == Status.CONVERGED

    def __repr__(self):
        """One line (the values and the NaN-padded history are long): status, cost, counts."""
        if isinstance(self.status, jax.core.Tracer) or np.ndim(self.status):
            return f"SolveResult(status={self.status!r}, cost={self.cost!r}, ...)"
        return (
            f"SolveResult(status={self.status_name}, cost={float(self.cost):.10g}, "
            f"iterations={int(self.iterations)}, linear_solves={int(self.linear_solves)}, "
            f"lambda_={float(self.lambda_):.3g}, values=<{len(self.values)} variable kinds>)"
        )
