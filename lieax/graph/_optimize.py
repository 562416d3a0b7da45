"""Levenberg-Marquardt on a pose graph, with GTSAM's `LevenbergMarquardtOptimizer` semantics.

One call runs the whole loop inside one jitted `lax.while_loop`: linearize every factor in closed
form (`lieax.graph.between_jacobians`), assemble the block-sparse normal equations by segment sums
over the edges into a fixed pattern, solve $(H + \\lambda I)\\,\\delta = -g$, retract
$X_k \\leftarrow X_k \\oplus \\delta_k$, and adapt $\\lambda$.

Semantics (GTSAM 4.3's defaults, so that iteration counts compare): $\\lambda_0 = 10^{-5}$, factor
10, $\\lambda \\ge 10^5$ gives up; a step is taken when the model fidelity (actual over predicted
cost decrease) exceeds $10^{-3}$, otherwise $\\lambda$ grows and the same linearization is solved
again; an outer iteration ends with a taken step, or without one when the cost change is below
`relative_tolerance` × cost; the run stops when the cost decrease of an iteration is at most
`absolute_tolerance` or `relative_tolerance` × cost, or after `max_iterations` iterations.
"""

import dataclasses
import hashlib

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax

from ..lstsq import Status
from ._factors import between_jacobians, prior_jacobian, robust_weights, whiten
from ._sparse import BlockPattern, CholeskyPlan, cholesky_solve, dense_solve, pcg

_DENSE_LIMIT = 120  # unknowns up to which "cholesky" factors the dense matrix inside JAX

_SOLVERS = ("cholesky", "cg")


@dataclasses.dataclass(frozen=True)
class OptimizeResult:
    """What `optimize` returns.

    **Fields:**
    - `poses`: the optimized poses, in the order of `graph.vertex_ids`.
    - `cost`: $\\tfrac12 \\sum \\rho(r^\\top \\Omega r)$ at `poses` (GTSAM's `graph.error`).
    - `iterations`: outer iterations (linearizations), as GTSAM counts them.
    - `linear_solves`: factorizations (or conjugate-gradient solves), rejected steps included.
    - `status`: a `Status`.
    - `cost_history`: `(iterations + 1,)` numpy array: the initial cost, then after each iteration.
    - `lambda_`: the damping at the end.
    """

    poses: object
    cost: float
    iterations: int
    linear_solves: int
    status: Status
    cost_history: np.ndarray
    lambda_: float

    @property
    def converged(self) -> bool:
        return self.status == Status.CONVERGED


def optimize(
    graph,
    *,
    max_iterations=100,
    solver="cholesky",
    jacobian="exact",
    verbose=False,
    lambda_initial=1e-5,
    lambda_factor=10.0,
    lambda_max=1e5,
    relative_tolerance=1e-5,
    absolute_tolerance=1e-5,
    min_model_fidelity=1e-3,
    cg_tolerance=1e-8,
    cg_max_iterations=None,
):
    """Levenberg-Marquardt on a `PoseGraph` (see the module docstring for the semantics).

    **Arguments:**
    - `graph`: the `PoseGraph`; its poses are the initial values.
    - `max_iterations`: outer iterations at most.
    - `solver`: `"cholesky"` (default): the host's multifrontal block Cholesky
      (`lieax.graph.CholeskyPlan`, numpy and LAPACK, called back from the jitted loop; exact
      steps, so the iterates follow GTSAM's); graphs of at most 120 unknowns factor the dense
      matrix inside JAX instead. `"cg"`: block-Jacobi preconditioned conjugate
      gradients, all in JAX, for accelerators (no host round trip; inexact steps, slower to
      converge on poorly conditioned graphs).
    - `jacobian`: `"exact"` (default) differentiates the residual $\\mathrm{Log}(Z^{-1}X_i^{-1}X_j)$
      exactly (with $J_r^{-1}(e)$), so the optimizer converges to a stationary point of the cost.
      GTSAM 4.3's iterates match these (same iteration counts, final costs equal to 1e-12 on the
      shared sets). `"approximate"` drops $J_r^{-1}$, the "I before the Log" of GTSAM builds
      without `GTSAM_SLOW_BUT_CORRECT_BETWEENFACTOR`: cheaper, but its fixed points are not the
      cost's stationary points, so tight tolerances stop it early (up to 0.3% above the
      minimum on smallGrid3D).
    - `verbose`: print the cost, $\\lambda$ and the step's fate at every attempt.
    - the rest: the Levenberg-Marquardt parameters (GTSAM's defaults) and the conjugate-gradient
      tolerance and iteration limit (default $10\\,n\\,d$).

    The gauge: poses in `graph.fixed` are held constant; without any, and without priors, the
    first pose is. A graph with several connected components must anchor each one (a prior or
    a fixed pose), else `ValueError`: a disconnected graph is reported, not silently optimized.

    **Returns:** an `OptimizeResult`.
    """
    if solver not in _SOLVERS:
        raise ValueError(f"solver must be one of {_SOLVERS}, got {solver!r}.")
    if jacobian not in ("exact", "approximate"):
        raise ValueError(f"jacobian must be 'exact' or 'approximate', got {jacobian!r}.")
    if max_iterations < 0:
        raise ValueError(f"max_iterations must be non-negative, got {max_iterations}.")
    history_size = max(16, 1 << int(max_iterations).bit_length())  # > max_iterations, bucketed
    problem = _problem(
        graph, solver, jacobian == "exact", history_size, bool(verbose), cg_max_iterations
    )
    priors = graph.priors
    params = {
        "lambda_initial": lambda_initial,
        "lambda_factor": lambda_factor,
        "lambda_max": lambda_max,
        "relative_tolerance": relative_tolerance,
        "absolute_tolerance": absolute_tolerance,
        "min_model_fidelity": min_model_fidelity,
        "cg_tolerance": cg_tolerance,
    }
    dtype = graph.poses.dtype
    params = {k: jnp.asarray(v, dtype) for k, v in params.items()}
    params["max_iterations"] = jnp.asarray(max_iterations, jnp.int32)
    data = (
        graph.between.measured,
        graph.between.sqrt_information,
        graph.between.loss,
        None if priors is None else (priors.measured, priors.sqrt_information, priors.loss),
    )
    out = problem.run(graph.poses, data, params)
    poses, cost, iterations, solves, status, history, lam = jax.device_get(out)
    iterations = int(iterations)
    return OptimizeResult(
        poses=graph.group._wrap(jnp.asarray(poses)),
        cost=float(cost),
        iterations=iterations,
        linear_solves=int(solves),
        status=Status(int(status)),
        cost_history=np.asarray(history)[: iterations + 1],
        lambda_=float(lam),
    )


# ---- the problem: structure analysed once, the loop compiled once -------------------------------

_CACHE = {}
_CACHE_SIZE = 8


def _digest(*arrays):
    h = hashlib.blake2b(digest_size=16)
    for a in arrays:
        a = np.ascontiguousarray(a)
        h.update(str((a.dtype, a.shape)).encode())
        h.update(a.tobytes())
    return h.hexdigest()


def _problem(graph, solver, exact, history_size, verbose, cg_max_iterations):
    priors = graph.priors
    prior_index = np.zeros(0, np.int64) if priors is None else priors.index
    key = (
        graph.group,
        graph.num_poses,
        _digest(graph.between.i, graph.between.j, prior_index, graph.fixed),
        solver,
        exact,
        history_size,
        verbose,
        cg_max_iterations,
        type(graph.between.loss),
        None if priors is None else type(priors.loss),
    )
    problem = _CACHE.get(key)
    if problem is None:
        problem = _Problem(graph, solver, exact, history_size, verbose, cg_max_iterations)
        if len(_CACHE) >= _CACHE_SIZE:
            _CACHE.pop(next(iter(_CACHE)))
        _CACHE[key] = problem
    return problem


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


class _Problem:
    """The static structure of one graph (pattern, plan, gauge) and its compiled loop."""

    def __init__(self, graph, solver, exact, history_size, verbose, cg_max_iterations):
        n, d = graph.num_poses, graph.poses.tangent_dim
        fixed = gauge_fixed(graph)
        check_anchored(graph, fixed)
        i, j = graph.between.i, graph.between.j
        pattern, pair, flipped = BlockPattern.from_edges(n, d, i, j)
        self.pattern = pattern
        dense = solver == "cholesky" and n * d <= _DENSE_LIMIT
        self.plan = CholeskyPlan.analyze(pattern) if solver == "cholesky" and not dense else None
        is_fixed = np.zeros(n, dtype=bool)
        is_fixed[fixed] = True
        free_pair = ~(is_fixed[pattern.rows] | is_fixed[pattern.cols])
        prior_index = None if graph.priors is None else np.asarray(graph.priors.index)
        self.static = {
            "n": n,
            "d": d,
            "p": pattern.num_pairs,
            "solver": "dense" if dense else solver,
            "exact": exact,
            "history_size": history_size,
            "verbose": verbose,
            "cg_max_iterations": cg_max_iterations,
        }
        self.indices = {
            "i": jnp.asarray(i, jnp.int32),
            "j": jnp.asarray(j, jnp.int32),
            "pair": jnp.asarray(pair, jnp.int32),
            "flipped": jnp.asarray(flipped),
            "free": jnp.asarray(~is_fixed),
            "free_pair": jnp.asarray(free_pair),
            "prior": None if prior_index is None else jnp.asarray(prior_index, jnp.int32),
        }
        self._run = jax.jit(self._loop)

    def run(self, poses, data, params):
        return self._run(poses, data, params, self.indices)

    # ---- pieces of the loop (traced) ------------------------------------------------------------
    def _cost(self, poses, data, idx):
        measured, root, loss, prior = data
        from ._factors import between_error, prior_error

        e = between_error(poses[idx["i"]], poses[idx["j"]], measured)
        s = jnp.sum(whiten(root, e) ** 2, axis=-1)
        total = jnp.sum(robust_weights(loss, s)[0])
        if prior is not None:
            p_measured, p_root, p_loss = prior
            e = prior_error(poses[idx["prior"]], p_measured)
            s = jnp.sum(whiten(p_root, e) ** 2, axis=-1)
            total = total + jnp.sum(robust_weights(p_loss, s)[0])
        return 0.5 * total

    def _linearize(self, poses, data, idx):
        """`(cost, diag, off, g)` of the normal equations at `poses`, fixed poses masked."""
        st = self.static
        n, d, p = st["n"], st["d"], st["p"]
        measured, root, loss, prior = data
        e, J_i, J_j = between_jacobians(poses[idx["i"]], poses[idx["j"]], measured, st["exact"])
        r = whiten(root, e)
        J_i, J_j = root @ J_i, root @ J_j
        s = jnp.sum(r**2, axis=-1)
        rho, w = robust_weights(loss, s)
        cost = 0.5 * jnp.sum(rho)
        wJ_i, wJ_j = w[:, None, None] * J_i, w[:, None, None] * J_j
        Jt = lambda a: jnp.swapaxes(a, -1, -2)
        H_ii, H_jj, H_ij = Jt(wJ_i) @ J_i, Jt(wJ_j) @ J_j, Jt(wJ_i) @ J_j
        g_i = jnp.einsum("kba,kb->ka", wJ_i, r)
        g_j = jnp.einsum("kba,kb->ka", wJ_j, r)
        seg = jax.ops.segment_sum
        diag = seg(H_ii, idx["i"], n) + seg(H_jj, idx["j"], n)
        grad = seg(g_i, idx["i"], n) + seg(g_j, idx["j"], n)
        oriented = jnp.where(idx["flipped"][:, None, None], Jt(H_ij), H_ij)
        off = seg(oriented, idx["pair"], p)
        if prior is not None:
            p_measured, p_root, p_loss = prior
            e, J = prior_jacobian(poses[idx["prior"]], p_measured, st["exact"])
            r = whiten(p_root, e)
            J = p_root @ J
            s = jnp.sum(r**2, axis=-1)
            rho, w = robust_weights(p_loss, s)
            cost = cost + 0.5 * jnp.sum(rho)
            wJ = w[:, None, None] * J
            diag = diag + seg(Jt(wJ) @ J, idx["prior"], n)
            grad = grad + seg(jnp.einsum("kba,kb->ka", wJ, r), idx["prior"], n)
        free = idx["free"]
        eye = jnp.eye(d, dtype=diag.dtype)
        diag = jnp.where(free[:, None, None], diag, eye)
        grad = jnp.where(free[:, None], grad, 0.0)
        off = jnp.where(idx["free_pair"][:, None, None], off, 0.0)
        return cost, diag, off, grad

    def _solve(self, diag, off, rhs, params):
        st = self.static
        if st["solver"] == "dense":
            return dense_solve(self.pattern, diag, off, rhs)
        if st["solver"] == "cholesky":
            return cholesky_solve(self.plan, diag, off, rhs)
        x, _ = pcg(
            self.pattern,
            diag,
            off,
            rhs,
            tolerance=params["cg_tolerance"],
            max_iterations=st["cg_max_iterations"],
        )
        return x

    def _loop(self, poses, data, params, idx):
        """The Levenberg-Marquardt loop: one `while_loop` step per attempted damping; the
        linearization runs (inside a `cond`) at the start of each outer iteration, so it is
        traced once."""
        st = self.static
        group = type(poses)
        dtype = poses.dtype
        n, d, p = st["n"], st["d"], st["p"]
        eye = jnp.eye(d, dtype=dtype)
        cost = self._cost(poses, data, idx)
        history = jnp.full((st["history_size"],), jnp.nan, dtype).at[0].set(cost)
        status = jnp.where(
            jnp.isfinite(cost),
            jnp.where(params["max_iterations"] > 0, Status.RUNNING, Status.MAX_ITERATIONS),
            Status.NONFINITE,
        ).astype(jnp.int32)
        zero = jnp.zeros((), jnp.int32)
        system = (
            jnp.zeros((n, d, d), dtype),
            jnp.zeros((p, d, d), dtype),
            jnp.zeros((n, d), dtype),
        )
        state = (
            poses.parameters(),
            cost,
            system,
            jnp.array(True),
            params["lambda_initial"],
            zero,
            zero,
            status,
            history,
        )

        def cond(state):
            return state[7] == Status.RUNNING

        def body(state):
            x, cost, system, stale, lam, iterations, solves, status, history = state
            diag, off, grad = lax.cond(
                stale, lambda: self._linearize(group._wrap(x), data, idx)[1:], lambda: system
            )
            finite = jnp.all(jnp.isfinite(diag)) & jnp.all(jnp.isfinite(grad))
            delta = self._solve(diag + lam * eye, off, -grad, params)
            solved = finite & jnp.all(jnp.isfinite(delta))
            delta = jnp.where(solved, delta, 0.0)
            # predicted decrease of the undamped model: -g.δ - ½ δ.Hδ, with Hδ = -g - λδ
            predicted = -0.5 * jnp.vdot(grad, delta) + 0.5 * lam * jnp.vdot(delta, delta)
            candidate = group._wrap(group._normalize(group._wrap(x).rplus(delta).parameters()))
            new_cost = self._cost(candidate, data, idx)
            change = cost - new_cost
            valid = solved & (predicted >= 0) & jnp.isfinite(new_cost)
            fidelity = change / jnp.where(predicted > 0, predicted, 1.0)
            success = (
                valid
                & (predicted > jnp.finfo(dtype).eps * cost)
                & (fidelity > params["min_model_fidelity"])
            )
            stop_search = valid & ~success & (jnp.abs(change) < params["relative_tolerance"] * cost)
            new_lam = jnp.where(
                success, lam / params["lambda_factor"], lam * params["lambda_factor"]
            )
            gave_up = ~success & ~stop_search & (new_lam >= params["lambda_max"])
            iteration_done = success | stop_search | gave_up
            iterations = iterations + iteration_done.astype(jnp.int32)
            next_cost = jnp.where(success, new_cost, cost)
            decrease = cost - next_cost
            converged = iteration_done & (
                (decrease <= params["absolute_tolerance"])
                | (decrease <= params["relative_tolerance"] * cost)
            )
            status = jnp.where(
                ~finite,
                Status.NONFINITE,
                jnp.where(
                    gave_up & (decrease <= 0),
                    Status.DIVERGED,
                    jnp.where(
                        converged,
                        Status.CONVERGED,
                        jnp.where(
                            iteration_done & (iterations >= params["max_iterations"]),
                            Status.MAX_ITERATIONS,
                            Status.RUNNING,
                        ),
                    ),
                ),
            ).astype(jnp.int32)
            history = jnp.where(iteration_done, history.at[iterations].set(next_cost), history)
            if st["verbose"]:
                jax.debug.print(
                    "iteration {it:3d}  cost {c:.10g} -> {nc:.10g}  lambda {l:.1e}  "
                    "fidelity {f:.3f}  accepted {ok}",
                    it=iterations,
                    c=cost,
                    nc=new_cost,
                    l=lam,
                    f=fidelity,
                    ok=success,
                )
            x = jnp.where(success, candidate.parameters(), x)
            lam = jnp.where(iteration_done & ~success, lam, new_lam)
            return (
                x,
                next_cost,
                (diag, off, grad),
                success,
                lam,
                iterations,
                solves + 1,
                status,
                history,
            )

        x, cost, _, _, lam, iterations, solves, status, history = lax.while_loop(cond, body, state)
        return x, cost, iterations, solves, status, history, lam
