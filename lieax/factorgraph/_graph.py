"""`FactorGraph`: variables and factors, their structure analysed once, and `solve`.

The structure (index arrays, kinds, fixed instances, the Schur plan and the Cholesky plans) is
analysed on the host once and cached by a digest of the index arrays, as `lieax.graph.optimize`
caches its problems; values and factor data are arguments of the compiled loop, so a new start
or new measurements of the same structure reuse it, under `vmap` too.
"""

import operator
import warnings
from collections.abc import Iterable, Sequence

import jax
import jax.numpy as jnp
import numpy as np

from .._checks import to_device
from .._executable_store import traced as staged
from .._runtime_error import raise_if
from .._threads import lapack_limited
from .._typing import PyTree
from ..autodiff._tangents import check_retraction, manifold_leaves
from ..lstsq import (
    AbstractLoss,
    AbstractSolver,
    LevenbergMarquardt,
    NonFiniteStartError,
    SolveError,
    Status,
    Termination,
)
from ..lstsq._solution import SolveResult, is_failure, nonfinite_leaves
from ..retractions import Retraction, exp
from . import _multifrontal
from ._buckets import Buckets
from ._dense_solve import dense_threads
from ._elimination import (
    candidates,
    dense_cost,
    elimination_cost,
    factorization_bound,
    factorization_cost,
    formation_seconds,
    reduction_bound,
)
from ._factors import Factor, linearize_one, residual_one, variables_dtype
from ._implicit import solve_implicit
from ._solve import PARAMETERS, make_loop, numeric_options, static_options
from ._structure import analyze, digest, schur_layout
from ._variables import Var, instance

# padded unknowns up to which `linear_solver="auto"` factors the dense matrix in JAX where the
# multifrontal Cholesky runs its NumPy path (no native library, or not on the CPU): the crossover
# `lieax.graph.optimize` measured against that path's per-front costs. The native library's
# custom call is faster at every size measured (whole solves on prefixes of the g2o sets, one
# process, one pinned core, 2026-12-05: dense / multifrontal 1.06-1.09 at 30 unknowns, 1.1-1.3
# at 54-60, 1.4-2.0 at 90-120, 2.8-6.8 at 300), so with it "auto" is dense only for nearly dense
# factors (below)
_DENSE_LIMIT = 300
# ... and up to which it does so when the sparse factor would be nearly dense anyway (its
# multiply-adds at least `_DENSE_FILL` of the dense factorization's): a reduced camera system,
# where the fronts' fixed costs buy nothing (ladybug-49's: 441 unknowns, 68% of the block pairs
# present, a fully dense factor of 83% of the dense multiply-adds; its whole Schur solve took
# 0.7-0.85x the time dense, interleaved, load 8; the crossover for 9x9 blocks was measured
# between 441 and 1242 unknowns)
_DENSE_FILLED_LIMIT = 800
_DENSE_FILL = 0.5
_SOLVERS = ("auto", "dense", "cholesky", "cg")
GTSAM = LevenbergMarquardt.gtsam()  # `solve`'s default options (immutable, so shared)
GTSAM_TERMINATION = Termination.gtsam()
_CACHE = {}
_CACHE_SIZE = 16
_BUCKET_LOOPS = {}  # bucketed graphs' compiled loops, by `Buckets.key` and the options


class FactorGraph:
    """Factors over variable kinds, analysed once (a jaxls `LeastSquaresProblem`, a GTSAM
    `NonlinearFactorGraph` with its `Values`).

    **Arguments:**

    - `factors`: a sequence of `Factor`s (one per factor kind).
    - `variables`: the `Var`s, in the order of the solution's values (default: in the order the
      factors first name them).
    - `check_gauge`: `ValueError` when a connected component has no fixed variable and its
      unary factors constrain fewer directions than its variables have (see
      `_structure.check_anchored`; a partial prior counts only its constrained directions).
    - `buckets`: compile `solve`'s loop once per bucket of sizes instead of once per structure,
      for graphs that grow or change step by step (a sliding window, incremental SLAM in a
      Python loop). Each kind's instance count is padded to `_buckets.bucket_size` of it (two
      buckets per doubling: 50 → 64, 65 → 96, 97 → 128, 129 → 192; padded factor instances
      masked, padded variable instances held fixed, the solution cut back) and the structure
      (index arrays, block slots, the Cholesky plan's key) is an operand of the loop, not a
      constant of it: graphs whose counts fall in the same buckets, with the same kinds and
      options, share one compiled loop (kept by the module, across `FactorGraph`s). The solution
      equals the unbucketed one to rounding (sums in another order). Default `False`: a fixed
      structure's loop keeps its constants, which XLA specializes (measured in
      `benchmarks/sliding_window.py`). `linear_solver` `"dense"`, `"cg"` and `"cholesky"` are
      bucketed (`"auto"`: cholesky, or without the native library dense up to 300 padded
      unknowns of the buckets);
      `eliminate` (the Schur complement) is not: an explicit `Var` is a `ValueError`, `"auto"`
      eliminates nothing. `vmap` and implicit derivatives work; the derivatives' tangent
      program, `cost`, `linearize` and `marginal_covariances` keep the graph's own structure
      (compiled per structure, as without buckets).

    Construction validates everything that can be checked without compiling: index ranges,
    residual and information shapes (`jax.make_jaxpr` of one instance), positive-definite
    information, finite data, Jacobian shapes of a `jacobian_fn`.
    """

    def __init__(
        self,
        factors: Iterable[Factor],
        variables: Iterable[Var] | None = None,
        *,
        check_gauge: bool = True,
        buckets: bool = False,
    ):
        factors = tuple(factors)
        if not factors or not all(isinstance(f, Factor) for f in factors):
            raise TypeError("factors must be a non-empty sequence of lieax.factorgraph.Factor.")
        if variables is None:
            variables = []
            for f in factors:
                for v in f.vars:
                    if all(v is not w for w in variables):
                        variables.append(v)
        variables = tuple(variables)
        if not all(isinstance(v, Var) for v in variables):
            raise TypeError("variables must be lieax.factorgraph.Var objects.")
        for k, v in enumerate(variables):
            if v.name is None:
                v.name = f"var{k}"
        for k, f in enumerate(factors):
            if f.name is None:
                f.name = f"factor{k}"
            for v in f.vars:
                if all(v is not w for w in variables):
                    raise ValueError(f"factor kind {f.name!r} uses a Var not in variables.")
        self.factors = factors
        self.variables = variables
        shapes = {}  # kinds with one residual and the same argument shapes are traced once
        checked = [_check_factor(f, shapes) for f in factors]
        self.residual_dims = tuple(k for k, _ in checked)
        self.factor_traces = tuple(trace for _, trace in checked)  # for `_fingerprint`
        # the directions each unary factor constrains (the gauge check counts them)
        unary = (
            {k: constrained_directions(f) for k, f in enumerate(factors) if len(f.vars) == 1}
            if check_gauge
            else {}
        )
        # JAX's 64-bit mode when the graph was built: its host index arrays are traced into the
        # loop as constants, and JAX keeps their 32-bit conversions across a later switch
        self._x64 = bool(jax.config.jax_enable_x64)
        key = (
            tuple(
                (jax.tree_util.tree_structure(v.value), v.leaf_dims, v.count, digest(v.fixed))
                for v in variables
            ),
            tuple(
                (
                    tuple(next(k for k, w in enumerate(variables) if w is v) for v in f.vars),
                    digest(*f.indices),
                )
                for f in factors
            ),
            check_gauge,
            tuple((k, digest(r)) for k, r in unary.items()),
            self._x64,
        )
        cached = _CACHE.get(key)
        if cached is None:
            cached = analyze(variables, factors, unary if check_gauge else None) + ({}, {})
            if len(_CACHE) >= _CACHE_SIZE:
                _CACHE.pop(next(iter(_CACHE)))
            _CACHE[key] = cached
        self.layout, self.plans, self._schur, self._loops = cached
        self._structure_key = key
        self._buckets = Buckets(self) if buckets else None
        self._cost = self._linearize = self._implicit = self._default_data = None
        self._programs = {}  # other compiled programs of this graph, by name and form
        # what `solve` checks a call against: its options (to the loop), the values' leaves
        self._prepared = {}
        self._params = {}  # `solve`'s numeric options, as the loop's array (`_parameters`)
        self._initial_leaves, self._initial_treedef = jax.tree_util.tree_flatten(
            self.initial_values
        )
        self._initial_shapes = [np.shape(x) for x in self._initial_leaves]

    def __repr__(self):
        return (
            f"FactorGraph({len(self.variables)} variable kinds, {len(self.factors)} factor "
            f"kinds, {self.layout.num_unknowns} unknowns)"
        )

    def index(self, var: Var) -> int:
        """The position of `var` in `variables` (and in a solution's `values`)."""
        for k, v in enumerate(self.variables):
            if v is var:
                return k
        raise ValueError(f"{var!r} is not a variable of this graph.")

    @property
    def initial_values(self) -> tuple[PyTree, ...]:
        return tuple(v.value for v in self.variables)

    @property
    def data(self) -> tuple[tuple[PyTree, jax.Array | None, AbstractLoss | None], ...]:
        """Per factor kind `(data, sqrt_information, loss)`, as `solve(data=...)` takes it."""
        if self._default_data is None:
            self._default_data = tuple(
                (
                    f.data,
                    None if f.sqrt_information is None else to_device(f.sqrt_information),
                    f.loss,
                )
                for f in self.factors
            )
        return self._default_data

    def cost(
        self, values: Sequence[PyTree] | None = None, data: Sequence[PyTree] | None = None
    ) -> jax.Array:
        r"""$\tfrac12 \sum \rho(\|R r\|^2)$ at `values` (default the initial values; jitted,
        compiled once per graph)."""
        from ._assembly import cost

        self._check_x64()
        if self._cost is None:  # one compilation, not one per operation on first use
            self._cost = jax.jit(lambda v, d: cost(self.factors, self.plans, v, d))
        values = self.initial_values if values is None else tuple(values)
        return self._cost(values, self._data(data))

    def linearize(
        self, values: Sequence[PyTree] | None = None, data: Sequence[PyTree] | None = None
    ) -> tuple[jax.Array, tuple[jax.Array, ...], tuple[jax.Array, ...], tuple[jax.Array, ...]]:
        """`(cost, diag, off, grad)`: the block normal equations at `values` (fixed instances
        masked), per kind and per pair of kinds of `layout` (jitted, compiled once per graph)."""
        from ._assembly import linearize

        self._check_x64()
        if self._linearize is None:
            self._linearize = jax.jit(
                lambda v, d: linearize(self.layout, self.factors, self.plans, v, d)
            )
        values = self.initial_values if values is None else tuple(values)
        return self._linearize(values, self._data(data))

    def _linearized_system(self, values, data):
        """The undamped normal equations `(diag, off, grad)` per kind of `layout` at `values`
        (fixed instances masked), from the graph's latest compiled solve loop stopped after its
        first evaluation (`max_iterations` 0): the program that solved the graph serves its
        marginals, with no compilation of their own. Before any `solve`, and for a bucketed
        graph (whose loop holds the buckets' system), `linearize` gives them (one program of
        the structure, smaller than a loop)."""
        if self._buckets is not None or not self._prepared:
            return self.linearize(values, data)[1:]
        loop = next(reversed(self._prepared.values()))[0]
        leaves = self._checked_leaves(values)
        params = self._parameters(
            GTSAM, GTSAM_TERMINATION, 1e-8, np.result_type(*(x.dtype for x in leaves))
        ).copy()
        params[PARAMETERS.index("max_iterations")] = 0
        return loop(values, data, params)[2]

    def _check_x64(self):
        """`ValueError` when JAX's 64-bit mode changed since the graph was built: its arrays
        (values, data, and the structure's index arrays, whose conversions JAX keeps) have the
        widths of the mode they were made in, so the solve would run in float32 after
        `jax_enable_x64` was switched on, or fail on mixed integer widths. A graph built again
        in the new mode gets a structure of its own (the cache is keyed by the mode)."""
        x64 = bool(jax.config.jax_enable_x64)
        if x64 != self._x64:
            raise ValueError(
                f"this FactorGraph was built with jax_enable_x64={self._x64} and is used with "
                f"jax_enable_x64={x64}: build its Vars, Factors and FactorGraph again after "
                "switching (better: set jax_enable_x64 once, at startup, before making arrays)."
            )

    def _data(self, data):
        if data is None:
            return self.data
        data = tuple(data)
        if len(data) != len(self.factors):
            raise ValueError(f"data must have one entry per factor kind ({len(self.factors)}).")
        return tuple(d if d is not None else default for d, default in zip(data, self.data))

    def solve(
        self,
        values: Sequence[PyTree] | None = None,
        data: Sequence[PyTree] | None = None,
        *,
        solver: AbstractSolver = GTSAM,
        termination: Termination = GTSAM_TERMINATION,
        linear_solver: str = "auto",
        eliminate: Var | str | None = "auto",
        retraction: Retraction | None = None,
        cg_tolerance: float = 1e-8,
        cg_max_iterations: int | None = None,
        verbose: bool = False,
        throw: bool = True,
    ) -> SolveResult:
        r"""Minimize $\tfrac12 \sum \rho(\|R r\|^2)$ (see `_solve` for the semantics).

        **Arguments:**

        - `values`: starting values, a tuple in the order of `variables` (default the `Var`s').
        - `data`: per factor kind `(data, sqrt_information, loss)` or `None` to keep the
          factor's own (see `FactorGraph.data`); may be traced, batched under `vmap` and
          differentiated (implicit derivatives, `_implicit`).
        - `solver`: the options of lieax's Levenberg-Marquardt, a
          `lieax.lstsq.LevenbergMarquardt` (the default is `LevenbergMarquardt.gtsam()`:
          GTSAM 4.3's damping $\mu I$, $\mu_0 = 10^{-5}$, ×10 / ÷10, give up at $10^5$; pass
          e.g. `LevenbergMarquardt.gtsam(scaling="clipped", damping_update="nielsen")` for the
          Marquardt diagonal with Nielsen's rule, or `LevenbergMarquardt.ceres()`), or
          `lieax.lstsq.GaussNewton()`. This backend supports the scalings `"identity"`,
          `"clipped"` and `"jacobi"` and the damping updates `"gtsam"` and `"nielsen"`;
          GTSAM's ×10 / ÷10 with a diagonal scaling ping-pongs between two dampings (see
          `_solve`).
        - `termination`: when to stop, a `lieax.lstsq.Termination` (default
          `Termination.gtsam()`: 100 outer iterations, linearizations as GTSAM counts them;
          `function_tolerance` and `absolute_function_tolerance` $10^{-5}$, GTSAM's
          `relativeErrorTol` and `absoluteErrorTol`; see `_solve`). This loop counts
          `counting="outer"` and runs no gradient or step test (`gradient_tolerance` and
          `parameter_tolerance` 0); it refuses other settings with a `ValueError`.
        - `linear_solver`: `"dense"`, `"cholesky"` (host multifrontal), `"cg"` (block-Jacobi
          PCG) or `"auto"` (dense up to 800 padded unknowns when the sparse factor would be at
          least half dense, else cholesky; without the native library, dense up to 300 padded
          unknowns too); with `eliminate`, the solver of the reduced system.
        - `eliminate`: a `Var` to eliminate by the Schur complement (its instances must not
          share factors: points in bundle adjustment), `None` for none, or `"auto"`: the kind
          whose elimination makes a linear solve cheapest by the cost model of
          `_elimination` (the multifrontal Cholesky's: the modelled time of forming and
          factoring the reduced system, against factoring the whole), or none when none
          pays: points seen by a few cameras are eliminated, landmarks seen by most poses
          are not (they would make the reduced pose system dense). An explicit `Var` that the
          model finds costlier than no elimination is still eliminated, with a `UserWarning`
          naming both costs.
        - `retraction`: how a step moves the values, a `lieax.retractions.Retraction` (default
          `lieax.retractions.exp`, $x \oplus \delta$; `cayley` is GTSAM's default Pose3 chart).
          The Jacobians and the optimum do not depend on it, the path to the optimum does.
        - `cg_tolerance`, `cg_max_iterations`: of `linear_solver="cg"` (relative residual;
          default $10\,n\,d$ iterations).
        - `verbose`: print iteration, cost, gain ratio and damping at every attempt.
        - `throw`: raise `SolveError` when the solve ends `DIVERGED` or `NONFINITE`;
          `lieax.lstsq.NonFiniteStartError` (also a `ValueError`) naming the values or factor
          data that hold NaN or infinite entries when the start was not finite (the result then
          holds the values unchanged, 0 iterations). Under `jit` the `SolveError` is raised when
          the compiled program runs (JAX's runtime error, carrying its message); under `vmap`
          nothing is raised: read each problem's `status`.

        **Returns:** a `SolveResult`.
        """
        self._check_x64()
        if not isinstance(termination, Termination):
            raise TypeError(f"termination must be a lieax.lstsq.Termination, got {termination!r}.")
        termination.require(
            "FactorGraph.solve", "outer", zero=("gradient_tolerance", "parameter_tolerance"),
            given=("function_tolerance", "absolute_function_tolerance"),
        )  # fmt: skip
        loop, layout, method = self._loop(
            solver, linear_solver, eliminate, termination.max_iterations, retraction, verbose,
            cg_max_iterations,
        )  # fmt: skip
        if values is None:
            values = self.initial_values  # checked by the `Var`s
            leaves = self._initial_leaves
        else:
            values = tuple(values)
            leaves = self._checked_leaves(values)
        data = self._data(data)
        params = self._parameters(
            solver, termination, cg_tolerance, np.result_type(*(x.dtype for x in leaves))
        )
        if self._buckets is not None:  # padded to the buckets, the structure an operand
            loop = self._buckets.runner(loop, method)
        # under a transformation or a staging (values or data traced, or a `jit` of a function
        # that solves with concrete ones): the solve with its implicit derivatives, whose
        # results may be traced
        if staged((values, data), {}):
            result = _result(*solve_implicit(self, loop, values, data, params))
        else:  # one dispatch, one transfer of the scalars: they come back as NumPy values
            threads = dense_threads(layout.pattern) if method == "dense" else None
            with lapack_limited(threads):  # waits for the program (`np.asarray`) inside
                solution, summary, _ = loop(values, data, params)
                summary = np.asarray(summary)
            result = _result(solution, summary)
        if throw:
            result = _raise_on_failure(self, result, values, data)
        return result

    def _parameters(self, solver, termination, cg_tolerance, dtype):
        """The loop's array of `_solve.PARAMETERS` (`solver`'s constants, `termination`'s
        tolerances and iteration limit, `cg_tolerance`, in the values' `dtype`), kept by
        their values: a repeated call reuses it."""
        try:
            key = (solver, termination, cg_tolerance, dtype)
            params = self._params.get(key)
        except TypeError:  # an unhashable value: built, not kept
            key, params = None, None
        if params is None:
            options = numeric_options(solver, termination, cg_tolerance)
            params = np.asarray([options[name] for name in PARAMETERS], dtype)
            params.flags.writeable = False
            if key is not None:
                if len(self._params) >= 16:
                    self._params.clear()
                self._params[key] = params
        return params

    def _loop(
        self, solver, linear_solver, eliminate, max_iterations, retraction, verbose,
        cg_max_iterations,
    ):  # fmt: skip
        """`(loop, layout, method)`: the compiled `run(values, data, params) -> (values, summary)`
        of `solve`'s options (`_solve.make_loop`), the layout its linear solver works on and that
        solver, kept by the options: a repeated call skips their checks."""
        static = static_options(solver)
        try:
            key = (static, linear_solver, eliminate, max_iterations, retraction, verbose,
                   type(cg_max_iterations), cg_max_iterations)  # fmt: skip
            prepared = self._prepared.get(key)
        except TypeError:  # an unhashable argument: checked (and refused) below
            key, prepared = None, None
        # `"auto"` is decided again at every call (cheap), so that the limits stay live
        if prepared is None or (
            linear_solver == "auto" and _auto_method(prepared[1]) != prepared[2]
        ):
            prepared = self._prepare(
                static, linear_solver, eliminate, max_iterations, retraction, verbose,
                cg_max_iterations,
            )  # fmt: skip
            if key is not None:
                self._prepared[key] = prepared
        return prepared

    def _prepare(
        self, static, solver, eliminate, max_iterations, retraction, verbose, cg_max_iterations
    ):
        """`(loop, layout, method)`: the compiled loop of `solve`'s options (`static`, from
        `_solve.static_options`; `solver`, the linear solver), each checked, the layout its
        linear solver works on and that solver (`solve` keeps them by the options, so a repeated
        call skips the checks)."""
        if solver not in _SOLVERS:
            raise ValueError(f"linear_solver must be one of {_SOLVERS}, got {solver!r}.")
        if cg_max_iterations is not None:
            cg_max_iterations = _count(cg_max_iterations, "cg_max_iterations")
        retraction = exp if retraction is None else check_retraction(retraction)
        schur = None
        layout = self.layout
        e = self._eliminated(eliminate, solver)
        if e is not None:
            schur = self._schur.get(e)
            if schur is None:
                schur = self._schur[e] = schur_layout(
                    self.layout, e, self._names(), self._schur.get(("reduced", e))
                )
            layout = schur.layout
        if self._buckets is not None:
            layout = self._buckets
        if solver == "auto":
            solver = _auto_method(layout)
        if solver == "cholesky" and self._buckets is None:
            layout.start_plan()  # analysed while the loop is traced and compiled
        gauss_newton, scaling, damping_update, floor, inclusive_gain, inclusive_damping = static
        options = {
            "method": solver,
            "schur": schur,
            "scaling": scaling,
            "damping_update": damping_update,
            "gauss_newton": gauss_newton,
            "floor": floor,
            "inclusive_gain_ratio": inclusive_gain,
            "inclusive_max_damping": inclusive_damping,
            "retraction": retraction,
            "history_size": max(16, 1 << int(max_iterations).bit_length()),
            "verbose": bool(verbose),
            "cg_max_iterations": cg_max_iterations,
        }
        key = (
            tuple((f.residual, f.jacobian_fn, f.data is None) for f in self.factors),
            None if schur is None else schur.eliminated,
            *(
                options[k]
                for k in (
                    "method",
                    "scaling",
                    "damping_update",
                    "gauss_newton",
                    "floor",
                    "inclusive_gain_ratio",
                    "inclusive_max_damping",
                    "retraction",
                    "history_size",
                    "verbose",
                    "cg_max_iterations",
                )
            ),
        )
        if self._buckets is not None:  # one loop for all graphs of these buckets
            key = (self._buckets.key, *key)
            loop = _BUCKET_LOOPS.get(key)
            if loop is None:
                if len(_BUCKET_LOOPS) >= _CACHE_SIZE:
                    _BUCKET_LOOPS.pop(next(iter(_BUCKET_LOOPS)))
                loop = _BUCKET_LOOPS[key] = make_loop(self._buckets, options)
            return loop, layout, solver
        loop = self._loops.get(key)
        if loop is None:
            # the Cholesky plan registered before the loop runs (`_native_cholesky`): tracing
            # the loop waits for it; a loop `lieax._executable_store` loaded waits after loading
            ready = layout.plan if solver == "cholesky" else None
            loop = self._loops[key] = make_loop(self, options, ready)
        return loop, layout, solver

    def _names(self):
        return [v.name for v in self.variables]

    def _eliminated(self, eliminate, solver):
        """The kind `solve(eliminate=...)` eliminates, or `None` (see `solve`; the costs are
        kept with the structure, per solver)."""
        if eliminate is None or (self._buckets is not None and eliminate == "auto"):
            return None
        if self._buckets is not None:
            raise ValueError(
                "FactorGraph(buckets=True) does not support eliminate= (the Schur complement's "
                "Gram plans are per structure, not bucketed): pass eliminate=None or 'auto' "
                "(which eliminates nothing under buckets), or build the graph without buckets."
            )
        if isinstance(eliminate, str):
            if eliminate != "auto":
                raise ValueError(f"eliminate must be a Var, None or 'auto', got {eliminate!r}.")
            key = ("auto", solver)
            if key not in self._schur:
                self._schur[key] = self._cheapest_elimination(solver)
            return self._schur[key]
        e = self.index(eliminate)
        cost = self._elimination_cost(e, solver)
        # below the whole system's bound it pays (the whole is not analysed to say so)
        whole = (
            None if cost.total < self._whole_bound(solver) else self._elimination_cost(None, solver)
        )
        if whole is not None and cost.total > whole.total:
            warnings.warn(
                f"eliminating {self.variables[e].name!r} by the Schur complement is predicted to "
                f"cost more than not eliminating: {cost.describe()} against "
                f"{whole.describe()} for the whole system. Pass eliminate='auto' (the default) "
                "or None.",
                stacklevel=5,
            )
        return e

    def _cheapest_elimination(self, solver):
        """The kind whose elimination makes a solve by `solver` cheapest, or `None` when no
        elimination beats the whole system (`_elimination`). A candidate whose formation alone
        costs more is passed over without building its reduced pattern (as large as its fill:
        every pair of points of a camera); the whole system's factorization is analysed only
        when the best candidate does not beat its lower bound."""

        def whole():
            return self._elimination_cost(None, solver).total

        bound = self._whole_bound(solver)
        formation = {k: formation_seconds(self.layout, k) for k in candidates(self.layout)}
        best, least = None, np.inf
        for k in sorted(formation, key=formation.get):
            lower = formation[k] + self._reduction_bound(k, solver)
            if lower >= least or (lower >= bound and lower >= whole()):
                continue
            cost = self._elimination_cost(k, solver).total
            if cost < least:
                best, least = k, cost
        return best if best is not None and (least < bound or least < whole()) else None

    def _reduction_bound(self, e, solver):
        """A lower bound of the modelled cost of factoring the system reduced by eliminating kind
        `e` with `solver`: the sparse factor's (`_elimination.reduction_bound`), or the dense
        one's (exact, from the size alone) where `solver` may pick it (`_auto_method`)."""
        d = max(dim for k, dim in enumerate(self.layout.dims) if k != e)
        n = d * sum(count for k, count in enumerate(self.layout.counts) if k != e)
        dense = dense_cost(n)
        if solver == "dense":
            return dense
        sparse = reduction_bound(self.layout, e)
        return sparse if solver == "cholesky" or n > _DENSE_FILLED_LIMIT else min(dense, sparse)

    def _whole_bound(self, solver):
        """A lower bound of the modelled cost of a solve by `solver` without elimination: the
        sparse factor's (`_elimination.factorization_bound`), where `"auto"` cannot pick the
        dense one, else the cost itself."""
        small = solver != "cholesky" and self.layout.padded_unknowns <= _DENSE_FILLED_LIMIT
        if solver == "dense" or small:
            return self._elimination_cost(None, solver).total
        return factorization_bound(self.layout)

    def _elimination_cost(self, e, solver):
        """The `_elimination.SolveCost` of a solve by `solver` eliminating kind `e` (`None`:
        none), kept with the structure."""
        key = ("cost", e, solver)
        if key not in self._schur:

            def method_of(layout):
                return solver if solver in ("dense", "cholesky") else _auto_method(layout)

            if e is None:
                self._schur[key] = factorization_cost(self.layout, method_of(self.layout))
            else:
                cost, reduced = elimination_cost(self.layout, e, self._names(), method_of)
                self._schur[key] = cost
                self._schur.setdefault(("reduced", e), reduced)
        return self._schur[key]

    def _checked_leaves(self, values):
        """The array leaves of `values` when they have the structure, shapes and floating
        dtypes of the `Var`s' (one flatten); otherwise `_check_values` names the problem."""
        leaves, treedef = jax.tree_util.tree_flatten(values)
        if treedef == self._initial_treedef and all(
            getattr(x, "dtype", None) is not None and x.dtype.kind == "f" and x.shape == shape
            for x, shape in zip(leaves, self._initial_shapes)
        ):
            return leaves
        self._check_values(values)
        return leaves

    def _check_values(self, values):
        if len(values) != len(self.variables):
            raise ValueError(
                f"values must have one entry per variable kind ({len(self.variables)})."
            )
        for v, value in zip(self.variables, values):
            leaves, treedef = manifold_leaves(value, f"values[{v.name!r}]")
            if treedef != v.treedef or _kinds(leaves) != _kinds(manifold_leaves(v.value)[0]):
                raise ValueError(f"values for {v.name!r} must have the structure of its Var.")
            shapes = [jnp.shape(getattr(x, "_params", x)) for x in leaves]
            expected = [jnp.shape(getattr(x, "_params", x)) for x in manifold_leaves(v.value)[0]]
            if shapes != expected:
                raise ValueError(
                    f"values for {v.name!r} have shapes {shapes}, expected {expected}."
                )


def _auto_method(layout):
    """The solver `linear_solver="auto"` picks for `layout`: `"dense"` when its factor is nearly
    dense and it is small enough (see `_DENSE_FILLED_LIMIT`), or, without the native multifrontal
    Cholesky, when it is small (`_DENSE_LIMIT`); else `"cholesky"`. For a bucketed graph
    (`Buckets`) by its bucketed size alone, the same for every graph of its buckets."""
    n = layout.padded_unknowns
    limit = 0 if _multifrontal.native() else _DENSE_LIMIT
    if isinstance(layout, Buckets):
        return "dense" if n <= limit else "cholesky"
    if n <= limit or (
        n <= _DENSE_FILLED_LIMIT and layout.plan().stats["flops"] >= _DENSE_FILL * n**3 / 3
    ):
        return "dense"
    return "cholesky"


def _traced_error(code) -> SolveError:
    return SolveError(
        f"the factor graph solve ended {Status(code).name} (raised from inside jit; pass "
        "throw=False to read the result's status instead)."
    )


def _raise_on_failure(graph, result, values, data):
    """`result`, after raising the `SolveError` its status calls for (`solve`'s `throw`): now when
    the status is concrete, when the compiled program runs under `jit`, never under `vmap`."""
    if isinstance(result.status, jax.core.Tracer):
        return result._replace(status=raise_if(result.status, is_failure, _traced_error))
    status = Status(int(result.status))
    if status == Status.NONFINITE and int(result.iterations) == 0:
        inputs = _nonfinite_inputs(graph, values, data)
        if inputs:
            raise NonFiniteStartError(
                "the factor graph solve ended NONFINITE at its start: "
                f"{'; '.join(inputs)}. The result holds the values unchanged (pass "
                "throw=False to get it back)."
            )
    if status in (Status.DIVERGED, Status.NONFINITE):
        raise SolveError(
            f"the factor graph solve ended {status.name} after {int(result.iterations)} "
            f"iterations (cost {float(result.cost):.6g}); pass throw=False to get the "
            "result back."
        )
    return result


def _nonfinite_inputs(graph, values, data):
    """The values and factor data with NaN or infinite entries, named by variable and factor
    kind (`nonfinite_leaves`: concrete floating leaves only; computed when a solve has failed)."""
    named = [(f"values[{v.name!r}]", value) for v, value in zip(graph.variables, values)]
    named += [(f"data of factor {f.name!r}", d) for f, d in zip(graph.factors, data)]
    return [f"{name} has NaN or infinite entries" for name, tree in named if nonfinite_leaves(tree)]


def _kinds(leaves):
    """Each leaf's group type, or `"array"` (an array under `vmap` is a tracer, not an Array)."""
    return [type(x) if hasattr(x, "_params") else "array" for x in leaves]


def _count(value, name):
    """`value` as a non-negative Python int (an int or a NumPy integer, by `operator.index`)."""
    try:
        count = operator.index(value)
    except TypeError:
        raise ValueError(f"{name} must be a non-negative int, got {value!r}.") from None
    if count < 0:
        raise ValueError(f"{name} must be non-negative, got {count}.")
    return count


def _result(solution, summary):
    """The `SolveResult` of the loop's `summary` (`[cost, damping, iterations, solves, status,
    *history]`, a JAX array under transformations, else NumPy)."""
    iterations, solves, status = summary[2:5].astype(np.int32)  # one conversion for three
    return SolveResult(
        values=solution,
        cost=summary[0],
        iterations=iterations,
        linear_solves=solves,
        status=status,
        cost_history=summary[5:],
        damping=summary[1],
    )


def _argument_types(f, xs, data):
    """What the residual of `f` receives, for an error: each argument's type, and the data as
    arrays of their per-instance shapes (a residual that calls a group method on data rows
    wants the data as a lieax group, e.g. `lieax.SE2` batched `(m,)`, not `(x, y, theta)` rows)."""

    def described(x):
        if isinstance(x, jax.ShapeDtypeStruct):
            return f"an array {x.dtype}{list(x.shape)}"
        return type(x).__name__

    arguments = ", ".join(f"{described(x)} ({v.name!r})" for x, v in zip(xs, f.vars))
    text = f"it receives {arguments}"
    if data is not None:
        leaves = jax.tree_util.tree_leaves(data, is_leaf=lambda x: hasattr(x, "_params"))
        text += f" and data {', '.join(described(x) for x in leaves)} per instance"
    return (
        text + ": pass data that the residual calls group methods on as a lieax group batched "
        f"({f.count},), e.g. lieax.SE2.from_xy_theta(x, y, theta) or lieax.SE3(wxyz_xyz)."
    )


def _check_factor(f, shapes):
    """`(k, trace)`: the residual dimension `k` of factor kind `f` (also kept as
    `f.residual_size`), its shapes checked by `jax.make_jaxpr` (nothing is compiled) of the
    residual, or of the `jacobian_fn` when it has one (autodiff blocks are `(k, tangent_dim)` by
    construction; the linearization's trace cost 0.3-0.7 s a kind), and `trace`, `(xs, data,
    jaxpr)`: the shapes of one instance's arguments and that jaxpr (`_fingerprint` reads it);
    `shapes` keeps them by residual, `jacobian_fn` and argument shapes, for the kinds that share
    them. `ValueError`s name the factor kind."""
    m = f.count
    dtype = variables_dtype(f.vars)
    for path, leaf in jax.tree_util.tree_leaves_with_path(f.data):
        shape = jnp.shape(leaf)
        where = f"factor kind {f.name!r}: data{jax.tree_util.keystr(path)}"
        if not shape or shape[0] != m:
            raise ValueError(
                f"{where} must have leading axis {m} (one entry per instance, as every data "
                f"leaf), got shape {shape}."
            )
        leaf_dtype = jnp.result_type(leaf)
        if jnp.issubdtype(leaf_dtype, jnp.inexact) and leaf_dtype != dtype:
            # JAX would promote silently: float32 data in a float64 solve kept only 7 digits
            # (a UTM coordinate of 4e6 m to 0.25 m), float64 data in a float32 solve makes the
            # residual float64
            raise ValueError(
                f"{where} has dtype {leaf_dtype} but the factor's variables have dtype {dtype}; "
                f"give them one dtype (for example np.asarray(data, np.{dtype}))."
            )
        if isinstance(leaf, jax.core.Tracer):
            continue
        array = np.asarray(leaf)
        if np.issubdtype(array.dtype, np.inexact):
            bad = ~np.all(np.isfinite(array.reshape(m, -1)), axis=1)
            if np.any(bad):
                raise ValueError(
                    f"factor kind {f.name!r}: data of instance {int(np.argmax(bad))} is not finite."
                )
    xs = [jax.eval_shape(lambda v: instance(v, 0), var.value) for var in f.vars]
    one = (
        None
        if f.data is None
        else jax.tree_util.tree_map(
            lambda a: jax.ShapeDtypeStruct(jnp.shape(a)[1:], jnp.result_type(a)), f.data
        )
    )
    leaves, treedef = jax.tree_util.tree_flatten((xs, one))
    key = (f.residual, f.jacobian_fn, treedef, tuple((x.shape, x.dtype) for x in leaves))
    try:
        found = shapes.get(key)
    except TypeError:  # an unhashable residual or jacobian_fn
        key, found = None, None
    try:
        if found is not None:
            out, blocks, jaxpr = found
        elif f.jacobian_fn is None:
            jaxpr, out = jax.make_jaxpr(lambda xs, d: residual_one(f, xs, d), return_shape=True)(
                xs, one
            )
            blocks = None
        else:
            jaxpr, (out, blocks) = jax.make_jaxpr(
                lambda xs, d: linearize_one(f, xs, d), return_shape=True
            )(xs, one)
    except (TypeError, ValueError) as error:
        raise ValueError(
            f"factor kind {f.name!r}: its residual cannot be evaluated on one instance of its "
            f"arguments ({error})."
        ) from error
    except AttributeError as error:
        raise ValueError(
            f"factor kind {f.name!r}: its residual cannot be evaluated on one instance of its "
            f"arguments ({error}); {_argument_types(f, xs, one)}"
        ) from error
    if f.jacobian_fn is None and not isinstance(out, jax.ShapeDtypeStruct):
        raise ValueError(
            f"factor kind {f.name!r}: the residual must return one array (k,), got "
            f"{type(out).__name__} {jax.tree_util.tree_map(lambda x: x.shape, out)} (concatenate "
            "its parts, e.g. jnp.concatenate([r1, r2]))."
        )
    if len(out.shape) != 1:
        raise ValueError(
            f"factor kind {f.name!r}: the residual must be a vector (k,), got shape {out.shape}."
        )
    if key is not None:
        shapes[key] = out, blocks, jaxpr
    k = out.shape[0]
    f.residual_size = k
    for s, (block, var) in enumerate(zip(blocks or (), f.vars)):
        if block.shape != (k, var.tangent_dim):
            raise ValueError(
                f"factor kind {f.name!r}: the Jacobian block of argument {s} has shape "
                f"{block.shape}, expected ({k}, {var.tangent_dim})."
            )
    root = f.sqrt_information
    if root is not None:
        shape = jnp.shape(root)
        if shape not in ((k, k), (m, k, k)):
            raise ValueError(
                f"factor kind {f.name!r}: sqrt_information must have shape ({k}, {k}) or "
                f"({m}, {k}, {k}) for residuals of size {k}, got {shape}."
            )
        if not isinstance(root, jax.core.Tracer):
            batch = np.asarray(root, dtype=np.float64).reshape(-1, k, k)
            bad = ~np.all(np.isfinite(batch), axis=(1, 2)) | np.all(batch == 0, axis=(1, 2))
            if np.any(bad):
                raise ValueError(
                    f"factor kind {f.name!r}: sqrt_information {int(np.argmax(bad))} is not "
                    "finite or is all zero (a rank-deficient R constrains only some directions; "
                    "a zero R constrains none: drop the instance)."
                )
    return k, (xs, one, jaxpr)


def constrained_directions(f):
    """Per instance of factor kind `f`, how many directions its whitened residual constrains:
    the rank of its `sqrt_information` $R$ (its residual size `k` for the identity or a traced
    $R$), at most its variable's tangent dimension (for the gauge check of unary factors)."""
    k, dim = f.residual_size, sum(v.tangent_dim for v in f.vars)
    root = f.sqrt_information
    if root is None or isinstance(root, jax.core.Tracer):
        ranks = np.full(f.count, k)
    else:
        batch = np.asarray(root, dtype=np.float64).reshape(-1, k, k)
        ranks = np.broadcast_to(np.linalg.matrix_rank(batch), (f.count,))
    return np.minimum(ranks, dim)
