r"""Levenberg-Marquardt on a pose graph, with GTSAM's `LevenbergMarquardtOptimizer` semantics.

`optimize` is a short convenience over the public `lieax.factorgraph` API: the `PoseGraph`
becomes a `FactorGraph` of between factors $\mathrm{Log}(Z^{-1} X_i^{-1} X_j)$ and prior
factors $\mathrm{Log}(Z^{-1} X)$ with their closed-form blocks (`to_factor_graph`), built once
per structure (edges, priors, fixed poses) and solved by `FactorGraph.solve` with the graph's
poses and measurements as values and data, so that a new start or new measurements of the same
structure reuse its analysis and its compiled loop.

Semantics: `lieax.lstsq.LevenbergMarquardt.gtsam()`, GTSAM 4.3's defaults, so that iteration
counts compare: $\mu_0 = 10^{-5}$, factor 10, $\mu \ge 10^5$ gives up; a step is taken when
the model fidelity (actual over predicted cost decrease) exceeds $10^{-3}$, otherwise $\mu$
grows and the same linearization is solved again; `lieax.lstsq.Termination.gtsam()`: an outer
iteration ends with a taken step, or without one when the cost change is below
`function_tolerance` × cost; the run stops when the cost decrease of an iteration is at most
`absolute_function_tolerance` or `function_tolerance` × cost, or after `max_iterations`
iterations (`lieax.factorgraph._solve`).
"""

import dataclasses

import jax
import numpy as np

from .._executable_store import traced as staged
from ..groups import SE2, SE3
from ..lstsq import AbstractSolver, LevenbergMarquardt, Status, Termination
from ..lstsq._solution import SolverResult
from ..retractions import Retraction
from ._factor_graph import refuse_sightings, to_factor_graph
from ._graph import PoseGraph

_LINEAR_SOLVERS = ("cholesky", "cg")
_GTSAM = LevenbergMarquardt.gtsam()
_GTSAM_TERMINATION = Termination.gtsam()


@dataclasses.dataclass(frozen=True, repr=False)
class OptimizeResult(SolverResult):
    r"""What `optimize` returns (concrete NumPy and Python values); a `lieax.lstsq.SolverResult`,
    the host view of the `lieax.factorgraph.SolveResult` of its solve.

    **Fields:**

    - `poses`: the optimized poses, in the order of `graph.vertex_ids`.
    - `cost`: $\tfrac12 \sum \rho(r^\top \Omega r)$ at `poses` (GTSAM's `graph.error`).
    - `iterations`: outer iterations (linearizations), as GTSAM counts them.
    - `linear_solves`: factorizations (or conjugate-gradient solves), rejected steps included.
    - `status`: a `Status` (`status_name` reads its name).
    - `cost_history`: `(iterations + 1,)` numpy array: the initial cost, then after each iteration.
    - `damping`: the damping at the end.
    """

    poses: SE2 | SE3
    cost: float
    iterations: int
    linear_solves: int
    status: Status
    cost_history: np.ndarray
    damping: float

    _repr_fields = ("cost", "iterations", "linear_solves", "damping")


def optimize(
    graph: PoseGraph,
    *,
    solver: AbstractSolver = _GTSAM,
    termination: Termination = _GTSAM_TERMINATION,
    linear_solver: str = "cholesky",
    jacobian: str = "exact",
    retraction: Retraction | None = None,
    cg_tolerance: float = 1e-8,
    cg_max_iterations: int | None = None,
    verbose: bool = False,
) -> OptimizeResult:
    r"""Levenberg-Marquardt on a `PoseGraph` (see the module docstring for the semantics).

    **Arguments:**

    - `graph`: the `PoseGraph`; its poses are the initial values.
    - `solver`: the Levenberg-Marquardt options (default `LevenbergMarquardt.gtsam()`), as
      `FactorGraph.solve`'s.
    - `termination`: when to stop (default `lieax.lstsq.Termination.gtsam()`: GTSAM's
      `maxIterations` 100, `relativeErrorTol` and `absoluteErrorTol` $10^{-5}$), as
      `FactorGraph.solve`'s.
    - `linear_solver`: `"cholesky"` (default): exact steps, so the iterates follow GTSAM's,
      from the multifrontal block Cholesky (`FactorGraph.solve(linear_solver="auto")`): the
      native library's, called from the jitted loop, at every size, since it is faster than
      factoring the dense matrix inside JAX at every size measured (one pinned core, whole
      solves on prefixes of the g2o sets, 2026-12-05: dense / multifrontal time 1.06-1.09 at
      30 unknowns, 1.1-1.3 at 54-60, 1.4-2.0 at 90-120, 2.8-6.8 at 300, 4-17 at 600).
      Without the native library the multifrontal runs on NumPy through a host callback, whose
      per-front costs make the dense matrix faster up to 300 unknowns (poses × tangent
      dimension), which then use it (measured on that path: dense / multifrontal 0.3-0.4 at
      60-120 unknowns, 0.9 at 300, 2.1 at 540). `"cg"`: block-Jacobi preconditioned conjugate
      gradients, all in JAX, for accelerators (no host round trip; inexact steps, slower to
      converge on poorly conditioned graphs).
    - `jacobian`: `"exact"` (default) differentiates the residual $\mathrm{Log}(Z^{-1}X_i^{-1}X_j)$
      exactly (with $J_r^{-1}(e)$), so the optimizer converges to a stationary point of the cost.
      GTSAM 4.3's iterates match these (same iteration counts, final costs equal to 1e-12 on the
      shared sets). `"approximate"` drops $J_r^{-1}$, the "I before the Log" of GTSAM builds
      without `GTSAM_SLOW_BUT_CORRECT_BETWEENFACTOR`: cheaper, but its fixed points are not the
      cost's stationary points, so tight tolerances stop it early (up to 0.3% above the
      minimum on smallGrid3D).
    - `retraction`: how a step moves the poses, a `lieax.retractions.Retraction` (default
      `lieax.retractions.exp`, $X_i \mathrm{Exp}(\delta_i)$ as GTSAM with
      `GTSAM_POSE3_EXPMAP`; `lieax.retractions.cayley` is GTSAM's default Pose3 chart). The
      Jacobians and the optimum do not depend on it, the path to the optimum does.
    - `cg_tolerance`, `cg_max_iterations`: of `linear_solver="cg"` (default $10\,n\,d$
      iterations).
    - `verbose`: print the cost, the damping and the step's fate at every attempt.

    The gauge: poses in `graph.fixed` are held constant; without any, and without priors, the
    first pose is. A graph with several connected components must anchor each one (a prior or
    a fixed pose), else `ValueError`: a disconnected graph is reported, not silently optimized.
    A solve that ends `DIVERGED` or `NONFINITE` is returned, not raised: read `status`.
    Its results are concrete, so it refuses `jit`, `vmap` and `grad` (`TypeError`): inside them,
    solve `to_factor_graph(graph)[0]` with `FactorGraph.solve`.

    **Returns:** an `OptimizeResult`.
    """
    refuse_sightings(graph, "optimize")
    if staged((graph.poses,), {}):
        raise TypeError(
            "graph.optimize returns concrete NumPy values and cannot run under jit, vmap or grad: "
            "solve lieax.graph.to_factor_graph(graph)[0] with FactorGraph.solve inside them "
            "(its values and data may be traced and differentiated)."
        )
    if linear_solver not in _LINEAR_SOLVERS:
        raise ValueError(f"linear_solver must be one of {_LINEAR_SOLVERS}, got {linear_solver!r}.")
    if jacobian not in ("exact", "approximate"):
        raise ValueError(f"jacobian must be 'exact' or 'approximate', got {jacobian!r}.")
    result = _factor_graph(graph, jacobian == "exact").solve(
        (graph.poses,),
        factor_data(graph),
        solver=solver,
        linear_solver="auto" if linear_solver == "cholesky" else "cg",
        eliminate=None,
        termination=termination,
        retraction=retraction,
        cg_tolerance=cg_tolerance,
        cg_max_iterations=cg_max_iterations,
        verbose=verbose,
        throw=False,
    )
    iterations = int(result.iterations)
    return OptimizeResult(
        poses=result.values[0],
        cost=float(result.cost),
        iterations=iterations,
        linear_solves=int(result.linear_solves),
        status=Status(int(result.status)),
        cost_history=np.asarray(result.cost_history)[: iterations + 1],
        damping=float(result.damping),
    )


# ---- the factor graph of a structure, built once ------------------------------------------------

_CACHE = {}
_CACHE_SIZE = 8


def _structure_key(*arrays):
    """The index arrays of a structure as a hashable value (the cache key of `_factor_graph`):
    their dtypes, shapes and bytes (2 us on tinyGrid3D's arrays, against 5 for a blake2b digest
    of them; a warm `optimize` there takes about 330 us)."""
    return tuple((a.dtype.str, a.shape, a.tobytes()) for a in map(np.asarray, arrays))


def factor_data(graph):
    """The factor graph's data of `graph`: `(measured, sqrt_information, loss)` of the between
    factors, and of the priors when there are any."""
    b, p = graph.between, graph.priors
    if p is not None and len(p):
        return (b.measured, b.sqrt_information, b.loss), (p.measured, p.sqrt_information, p.loss)
    return ((b.measured, b.sqrt_information, b.loss),)


def _factor_graph(graph, exact):
    """The `FactorGraph` of `graph`'s structure (cached: a new start or new measurements of the
    same edges, priors and fixed poses reuse it, its analysis and its compiled loops)."""
    priors = graph.priors
    prior_index = np.zeros(0, np.int64) if priors is None else priors.index
    key = (
        graph.group,
        graph.num_poses,
        _structure_key(graph.between.i, graph.between.j, prior_index, graph.fixed),
        exact,
        bool(jax.config.jax_enable_x64),  # a `FactorGraph` is bound to the mode it was built in
    )
    factor_graph = _CACHE.get(key)
    if factor_graph is None:
        check_anchored(graph, gauge_fixed(graph))
        factor_graph, _ = to_factor_graph(graph, exact=exact, check_gauge=False)
        if len(_CACHE) >= _CACHE_SIZE:
            _CACHE.pop(next(iter(_CACHE)))
        _CACHE[key] = factor_graph
    return factor_graph


def gauge_fixed(graph):
    """The pose indices `optimize` holds constant: `graph.fixed`, else none when there are
    priors, else the first pose."""
    if len(graph.fixed):
        return np.asarray(graph.fixed, dtype=np.int64)
    if graph.priors is not None and len(graph.priors):
        return np.zeros(0, dtype=np.int64)
    return np.zeros(1, dtype=np.int64)


def check_anchored(graph, fixed):
    """`ValueError` unless every connected component has a fixed pose or a prior."""
    count, labels = graph.components()
    if count == 1:
        return
    anchored = np.zeros(count, dtype=bool)
    anchored[labels[fixed]] = True
    if graph.priors is not None:
        anchored[labels[graph.priors.index]] = True
    if not anchored.all():
        sizes = np.bincount(labels, minlength=count)
        free = np.flatnonzero(~anchored)
        described = ", ".join(
            f"{sizes[c]} poses from vertex {graph.vertex_ids[np.argmax(labels == c)]}"
            for c in free[:5]
        )
        raise ValueError(
            f"the graph has {count} disconnected components and {len(free)} of them have no "
            f"prior or fixed pose ({described}{', ...' if len(free) > 5 else ''}): their poses "
            "are not determined. Connect them, add priors (graph.with_prior) or fix a pose in "
            "each (graph.with_fixed)."
        )
