"""What a solve returns: the `Solution` pytree, the `Status` codes and the error `throw` raises."""

import enum
from typing import NamedTuple

import jax
import numpy as np


class Status(enum.IntEnum):
    """Why a solve stopped; `Solution.status` holds the integer code.

    - `CONVERGED`: a tolerance was met (step, relative cost change or gradient) after a tried
      step, or the start is exactly stationary (a zero gradient; `iterations == 0`).
    - `MAX_ITERATIONS`: `max_iterations` iterations ran without meeting a tolerance.
    - `DIVERGED`: the cost grew without bound (Gauss-Newton) or no damping, however large, made
      the cost decrease (Levenberg-Marquardt).
    - `NONFINITE`: the residual or its Jacobian was NaN or infinite at the current point (or,
      for Levenberg-Marquardt, at every trial point down to the smallest step). With
      `iterations == 0` the start itself: `x0`, `args` where the residual reads them, or a
      loss scale that is not positive and finite; the solution's `value` is then `x0`
      unchanged.

    `RUNNING` is the state inside the loop and is never returned.
    """

    RUNNING = -1
    CONVERGED = 0
    MAX_ITERATIONS = 1
    DIVERGED = 2
    NONFINITE = 3


def status_names(status, enum=Status):
    """The `enum` member names of integer status codes: one name, or an object array of names
    for a batch (needs concrete codes, outside `jit`)."""
    codes = np.asarray(status)
    names = np.vectorize(lambda code: enum(int(code)).name, otypes=[object])(codes)
    return names.item() if names.ndim == 0 else names


def is_failure(code) -> bool:
    """Whether a status code is one that `throw=True` raises for (`DIVERGED`, `NONFINITE`)."""
    return code in (Status.DIVERGED, Status.NONFINITE)


class SolveError(RuntimeError):
    """Raised by `least_squares(..., throw=True)` when a solve ends `DIVERGED` or `NONFINITE`."""


class NonFiniteStartError(SolveError, ValueError):
    """The `SolveError` of a solve that did not start because its input is not finite: NaN or
    infinite entries in `x0` or `args`, or a loss scale that is not positive and finite (the
    message names each by its pytree path). Also a `ValueError`: the input is at fault."""


class Solution(NamedTuple):
    r"""The result of `lieax.lstsq.least_squares`, a pytree (so it batches under `vmap`).

    **Fields:**
    - `value`: the solution, the same pytree as `x0` (groups and arrays mixed).
    - `cost`: $\tfrac12 \sum_i \rho(\|r_i\|^2)$ at `value` ($\tfrac12\|r\|^2$ without a
      loss).
    - `iterations`: iterations run, rejected Levenberg-Marquardt steps included.
    - `status`: an integer `Status` code; `status_name` reads it.
    - `cost_history`: shape `(max_iterations + 1,)`: the initial cost, then the cost after each
      iteration; NaN after the last one.
    """

    value: object
    cost: jax.Array
    iterations: jax.Array
    status: jax.Array
    cost_history: jax.Array

    @property
    def status_name(self):
        """The `Status` name (`"CONVERGED"`, ...), or an array of names for a batch of solutions.
        Needs a concrete status (outside `jit`)."""
        return status_names(self.status)

    @property
    def converged(self) -> jax.Array:
        """`status == Status.CONVERGED`, as a boolean array (works under `jit` and `vmap`)."""
        return self.status == Status.CONVERGED
