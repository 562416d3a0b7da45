"""What every lieax solver returns and raises: the `Status` codes, the `SolverResult` base of the
result types, the results of lieax's Levenberg-Marquardt through its two doors (`Solution` of
`least_squares`, `SolveResult` of `FactorGraph.solve`; `lieax.graph.OptimizeResult` is the host
view of a `SolveResult`), and `SolveError`, the base of the solvers' errors."""

import enum
from typing import NamedTuple

import jax
import numpy as np

from ..groups import AbstractManifold, kernels


class Status(enum.IntEnum):
    """Why a solver stopped, one enum for every lieax solver: the `status` of a `Solution`
    (`lieax.lstsq`), a `SolveResult` (`lieax.factorgraph`), an `OptimizeResult` (`lieax.graph`)
    and an `ICPResult` (`lieax.icp.Status` is this enum). The integer codes are fixed: a stored
    code keeps its meaning.

    - `CONVERGED`: a tolerance was met (step, relative cost change or gradient) after a tried
      step, or the start is exactly stationary (a zero gradient; `iterations == 0`).
    - `MAX_ITERATIONS`: `Termination.max_iterations` iterations ran without meeting a tolerance.
    - `DIVERGED`: the cost grew without bound (Gauss-Newton) or no damping, however large, made
      the cost decrease (Levenberg-Marquardt).
    - `NONFINITE`: the residual or its Jacobian was NaN or infinite at the current point (or,
      for Levenberg-Marquardt, at every trial point down to the smallest step). With
      `iterations == 0` the start itself: `x0`, `args` where the residual reads them, or a
      loss scale that is not positive and finite; the solution's `value` is then `x0`
      unchanged. ICP: a valid source or target point, target normal, covariance or `init` is
      NaN or infinite (`transform` is `init`, `iterations == 0`).
    - `DEGENERATE`: the data do not determine an update: for ICP, fewer than 6 pairs lay within
      `max_correspondence_distance` (empty or non-overlapping clouds) or the update was not
      finite; the result holds the last point reached.
    - `INVALID`: a traced parameter is out of range (concrete ones raise a `ValueError` when
      called): for ICP, `max_correspondence_distance` or the loss's scale not positive and
      finite, or a tolerance negative or not finite; the result holds the start unchanged,
      `iterations == 0`.

    Which solver returns which: `lieax.lstsq` and `lieax.factorgraph` (and so `lieax.graph`)
    return `CONVERGED`, `MAX_ITERATIONS`, `DIVERGED` and `NONFINITE`; `lieax.icp` returns
    `CONVERGED`, `MAX_ITERATIONS`, `NONFINITE`, `DEGENERATE` and `INVALID`. `RUNNING` is the
    state inside a loop and is never returned.
    """

    RUNNING = -1
    CONVERGED = 0
    MAX_ITERATIONS = 1
    DIVERGED = 2
    NONFINITE = 3
    DEGENERATE = 4
    INVALID = 5


def status_names(status):
    """The `Status` names of integer status codes: one name, or an object array of names for a
    batch (needs concrete codes, outside `jit`)."""
    codes = np.asarray(status)
    names = np.vectorize(lambda code: Status(int(code)).name, otypes=[object])(codes)
    return names.item() if names.ndim == 0 else names


def is_failure(code) -> bool:
    """Whether a status code is one that `throw=True` raises for, in every solver: `DIVERGED`,
    `NONFINITE`, `DEGENERATE`, `INVALID` (not `MAX_ITERATIONS`: that result is usable)."""
    return code in (Status.DIVERGED, Status.NONFINITE, Status.DEGENERATE, Status.INVALID)


def nonfinite_leaves(tree):
    """`(path, kind, bad, size)` of each concrete floating leaf of `tree` with NaN or infinite
    entries (`kind` is `" (SE3)"` for a group leaf, `""` for an array; `bad` of its `size`
    entries are not finite): the one report of a non-finite start, which `least_squares` and
    `FactorGraph.solve` word (traced leaves are skipped: their values are not known)."""
    found = []
    is_group = lambda node: isinstance(node, AbstractManifold)  # noqa: E731
    for path, leaf in jax.tree_util.tree_flatten_with_path(tree, is_leaf=is_group)[0]:
        kind = f" ({type(leaf).__name__})" if is_group(leaf) else ""
        leaf = kernels.carrier(leaf) if is_group(leaf) else leaf
        if isinstance(leaf, jax.core.Tracer) or not hasattr(leaf, "dtype"):
            continue
        array = np.asarray(leaf)
        if np.issubdtype(array.dtype, np.inexact) and not np.all(np.isfinite(array)):
            bad = int(array.size - np.count_nonzero(np.isfinite(array)))
            found.append((jax.tree_util.keystr(path), kind, bad, int(array.size)))
    return found


class SolveError(RuntimeError):
    """The error of every lieax solver: raised with `throw=True` when a solve ends in a failure
    status (`is_failure`): by `least_squares` and `FactorGraph.solve` (`DIVERGED`, `NONFINITE`)
    and by ICP (`lieax.icp.ICPError`, a subclass). Catch `SolveError` to catch them all."""


class NonFiniteStartError(SolveError, ValueError):
    """The `SolveError` of a solve that did not start because its input is not finite: NaN or
    infinite entries in `x0` or `args`, or a loss scale that is not positive and finite (the
    message names each by its pytree path). Also a `ValueError`: the input is at fault."""


class SolverResult:
    r"""The base of every lieax solver's result: `lieax.lstsq.Solution`,
    `lieax.factorgraph.SolveResult`, `lieax.graph.OptimizeResult` and `lieax.icp.ICPResult`
    (the pytree ones are `NamedTuple`s, so they batch under `vmap`).

    **Every result has:**

    - `status`: an integer `Status` code, why the solver stopped (one enum for all solvers).
    - `iterations`: the iterations run, as the solver counts them (its result's docstring says
      how).
    - `status_name`: the `Status` name (`"CONVERGED"`, ...), or an array of names for a batch;
      needs a concrete status (outside `jit`).
    - `converged`: `status == Status.CONVERGED` (a boolean array under `jit` and `vmap`).
    - a one-line `repr`: the status name and the scalar fields (a batch: the count of each
      status).

    **Least-squares results** (`Solution`, `SolveResult`, `OptimizeResult`) also have:
    - `cost`: $\tfrac12 \sum_i \rho(\|r_i\|^2)$ at the solution, residuals whitened by their
      square-root information ($\tfrac12\|r\|^2$ without a loss).
    - `cost_history`: the initial cost, then the cost after each iteration (NaN-padded to
      `max_iterations + 1` entries in the pytree results).
    """

    __slots__ = ()
    _repr_fields = ("cost", "iterations")  # the scalars `repr` shows after the status

    @property
    def status_name(self):
        """The `Status` name (`"CONVERGED"`, ...), or an array of names for a batch of results.
        Needs a concrete status (outside `jit`)."""
        return status_names(self.status)

    @property
    def converged(self):
        """`status == Status.CONVERGED`, as a boolean array (works under `jit` and `vmap`)."""
        return self.status == Status.CONVERGED

    def __repr__(self):
        """One line: the status name and `_repr_fields` (the solution itself and the
        NaN-padded history are long); a batch gives its statuses' counts, a traced result its
        status."""
        name = type(self).__name__
        if isinstance(self.status, jax.core.Tracer):
            return f"{name}(status={self.status!r}, ...)"
        if np.ndim(self.status):
            names, counts = np.unique(status_names(self.status).ravel(), return_counts=True)
            statuses = ", ".join(f"{n} x{c}" for n, c in zip(names, counts))
            return f"{name}(batch of shape {np.shape(self.status)}: {statuses})"
        fields = [f"status={self.status_name}"]
        fields += [f"{field}={_scalar(getattr(self, field))}" for field in self._repr_fields]
        return f"{name}({', '.join(fields)})"


def _scalar(value):
    """A scalar as `repr` writes it: an int, or a float to 10 significant digits."""
    if isinstance(value, jax.core.Tracer):
        return repr(value)
    array = np.asarray(value)
    if np.issubdtype(array.dtype, np.integer):
        return str(int(array))
    return f"{float(array):.10g}"


class _SolutionFields(NamedTuple):
    value: object
    cost: jax.Array
    iterations: jax.Array
    status: jax.Array
    cost_history: jax.Array


class Solution(SolverResult, _SolutionFields):
    r"""The result of `lieax.lstsq.least_squares`, a pytree (so it batches under `vmap`); a
    `SolverResult`.

    **Fields:**

    - `value`: the solution, the same pytree as `x0` (groups and arrays mixed).
    - `cost`: $\tfrac12 \sum_i \rho(\|r_i\|^2)$ at `value` ($\tfrac12\|r\|^2$ without a
      loss).
    - `iterations`: iterations run, rejected Levenberg-Marquardt steps included.
    - `status`: an integer `Status` code; `status_name` reads it.
    - `cost_history`: shape `(max_iterations + 1,)`: the initial cost, then the cost after each
      iteration; NaN after the last one.
    """

    __slots__ = ()


class _SolveResultFields(NamedTuple):
    values: tuple
    cost: jax.Array
    iterations: jax.Array
    linear_solves: jax.Array
    status: jax.Array
    cost_history: jax.Array
    damping: jax.Array


class SolveResult(SolverResult, _SolveResultFields):
    r"""The result of `lieax.factorgraph.FactorGraph.solve`, a pytree (so it batches under
    `vmap`); a `SolverResult`.

    **Fields:**

    - `values`: the solution, a tuple in the order of the graph's `variables`.
    - `cost`: $\tfrac12 \sum \rho(\|R r\|^2)$ at `values`.
    - `iterations`: outer iterations (linearizations), as GTSAM counts them.
    - `linear_solves`: linear solves, rejected steps included.
    - `status`: an integer `Status` code; `status_name` reads it.
    - `cost_history`: the initial cost, then the cost after each iteration; NaN after the last.
    - `damping`: the damping $\mu$ at the end (`LevenbergMarquardt`'s vocabulary).
    """

    __slots__ = ()
    _repr_fields = ("cost", "iterations", "linear_solves", "damping")
