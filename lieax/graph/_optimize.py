"""Levenberg-Marquardt on a pose graph, with GTSAM's `LevenbergMarquardtOptimizer` semantics.

One call runs the whole loop inside one jitted `lax.while_loop`: linearize every factor in closed
form (the blocks of `lieax.graph.between_jacobians`), assemble the block-sparse normal equations
by segment sums over the edges into a fixed pattern, solve $(H + \\lambda I)\\,\\delta = -g$,
retract $X_k \\leftarrow X_k \\oplus \\delta_k$, evaluate the cost there, and adapt $\\lambda$. The
cost evaluation of a taken step (relative poses, errors, whitened residuals) is the first half of
the next linearization; a rejected step costs one cost evaluation and a new solve.

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

from .. import retractions
from ..lstsq import Status
from ._factors import prior_error, prior_jacobian_at, robust_weights, whiten
from ._sparse import BlockPattern, CholeskyPlan, cholesky_solve, dense_solve, pcg

# unknowns (poses × tangent dimension) up to which "cholesky" factors the dense matrix inside JAX
# rather than calling the host's multifrontal factorization (the crossover measured in `optimize`'s
# docstring)
_DENSE_LIMIT = 300

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
    retraction=None,
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
    - `solver`: `"cholesky"` (default): exact steps, so the iterates follow GTSAM's. Graphs of
      more than 300 unknowns (poses × tangent dimension) use the host's multifrontal block
      Cholesky (`lieax.graph.CholeskyPlan`, numpy and LAPACK, called from the jitted loop);
      smaller ones factor the dense matrix inside JAX, which skips the host call and the
      per-front overheads. The crossover is measured (one CPU thread, whole `optimize` calls
      on prefixes of smallGrid3D and intel): dense / multifrontal time 0.3-0.4 at 60-120
      unknowns, 0.5-0.7 at 180-240, 0.9 at 300, 1.0-1.3 at 360, 2.1 at 540, 2.3 at 600 (the
      dense factorization's $O((nd)^3)$ work overtakes the fronts' fixed costs early).
      `"cg"`: block-Jacobi preconditioned conjugate gradients, all in JAX, for accelerators
      (no host round trip; inexact steps, slower to converge on poorly conditioned graphs).
    - `jacobian`: `"exact"` (default) differentiates the residual $\\mathrm{Log}(Z^{-1}X_i^{-1}X_j)$
      exactly (with $J_r^{-1}(e)$), so the optimizer converges to a stationary point of the cost.
      GTSAM 4.3's iterates match these (same iteration counts, final costs equal to 1e-12 on the
      shared sets). `"approximate"` drops $J_r^{-1}$, the "I before the Log" of GTSAM builds
      without `GTSAM_SLOW_BUT_CORRECT_BETWEENFACTOR`: cheaper, but its fixed points are not the
      cost's stationary points, so tight tolerances stop it early (up to 0.3% above the
      minimum on smallGrid3D).
    - `retraction`: how a step moves the poses, a `lieax.retractions.Retraction` (default
      `lieax.retractions.exp`, $X_i \\mathrm{Exp}(\\delta_i)$ as GTSAM with
      `GTSAM_POSE3_EXPMAP`; `lieax.retractions.cayley` is GTSAM's default Pose3 chart). The
      Jacobians and the optimum do not depend on it, the path to the optimum does.
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
    if retraction is None:
        retraction = retractions.exp
    if not isinstance(retraction, retractions.Retraction):
        raise TypeError(f"retraction must be a lieax.retractions.Retraction, got {retraction!r}.")
    problem = _problem(
        graph, solver, jacobian == "exact", history_size, bool(verbose), cg_max_iterations,
        retraction,
    )  # fmt: skip
    priors = graph.priors
    dtype = graph.poses.dtype
    # one host array for all parameters and one for all scalar outputs: each array crossing the
    # jit boundary costs a transfer, which matters on graphs that take a few hundred microseconds
    params = np.array(
        [
            lambda_initial,
            lambda_factor,
            lambda_max,
            relative_tolerance,
            absolute_tolerance,
            min_model_fidelity,
            cg_tolerance,
            max_iterations,
        ],
        dtype=dtype,
    )
    data = (
        graph.between.measured,
        graph.between.sqrt_information,
        graph.between.loss,
        None if priors is None else (priors.measured, priors.sqrt_information, priors.loss),
    )
    poses, summary = problem.run(graph.poses, data, params)
    summary = np.asarray(summary)
    cost, lam, iterations, solves, status = summary[:5]
    iterations = int(iterations)
    return OptimizeResult(
        poses=graph.group._wrap(poses),
        cost=float(cost),
        iterations=iterations,
        linear_solves=int(solves),
        status=Status(int(status)),
        cost_history=summary[5 : 5 + iterations + 1].copy(),
        lambda_=float(lam),
    )


_PARAMETERS = (
    "lambda_initial",
    "lambda_factor",
    "lambda_max",
    "relative_tolerance",
    "absolute_tolerance",
    "min_model_fidelity",
    "cg_tolerance",
    "max_iterations",
)


# ---- the problem: structure analysed once, the loop compiled once -------------------------------

_CACHE = {}
_CACHE_SIZE = 8


def _digest(*arrays):
    h = hashlib.blake2b(digest_size=16)
    for a in arrays:
        a = np.ascontiguousarray(a)
        h.update(f"{a.dtype.str}{a.shape}".encode())
        h.update(a.tobytes())
    return h.hexdigest()


def _problem(graph, solver, exact, history_size, verbose, cg_max_iterations, retraction):
    priors = graph.priors
    if solver == "cholesky" and graph.num_poses * graph.poses.tangent_dim <= _DENSE_LIMIT:
        solver = "dense"
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
        retraction,
        type(graph.between.loss),
        None if priors is None else type(priors.loss),
    )
    problem = _CACHE.get(key)
    if problem is None:
        problem = _Problem(
            graph, solver, exact, history_size, verbose, cg_max_iterations, retraction
        )
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

    def __init__(self, graph, solver, exact, history_size, verbose, cg_max_iterations, retraction):
        n, d = graph.num_poses, graph.poses.tangent_dim
        fixed = gauge_fixed(graph)
        check_anchored(graph, fixed)
        i, j = graph.between.i, graph.between.j
        pattern, pair, flipped = BlockPattern.from_edges(n, d, i, j)
        self.pattern = pattern
        self.plan = CholeskyPlan.analyze(pattern) if solver == "cholesky" else None
        is_fixed = np.zeros(n, dtype=bool)
        is_fixed[fixed] = True
        free_pair = ~(is_fixed[pattern.rows] | is_fixed[pattern.cols])
        prior_index = None if graph.priors is None else np.asarray(graph.priors.index)
        self.static = {
            "n": n,
            "d": d,
            "p": pattern.num_pairs,
            "solver": solver,
            "exact": exact,
            "history_size": history_size,
            "verbose": verbose,
            "cg_max_iterations": cg_max_iterations,
            "retraction": retraction,
        }
        self.indices = {
            "i": jnp.asarray(i, jnp.int32),
            "j": jnp.asarray(j, jnp.int32),
            "ij": jnp.asarray(np.concatenate([i, j]), jnp.int32),
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
    def _residuals(self, poses, data, idx):
        """`(cost, parts)` at `poses`: the cost, and what `_system` needs besides (relative
        poses, errors, whitened residuals, robust weights), so that an accepted step's cost
        evaluation is also the first half of its linearization."""
        measured, root, loss, prior = data
        relative = poses[idx["i"]].between(poses[idx["j"]])
        e = measured.between(relative).log()
        r = whiten(root, e)
        rho, w = robust_weights(loss, jnp.sum(r**2, axis=-1))
        cost = 0.5 * jnp.sum(rho)
        parts = [(relative, e, r, None if loss is None else w)]
        if prior is not None:
            p_measured, p_root, p_loss = prior
            e = prior_error(poses[idx["prior"]], p_measured)
            r = whiten(p_root, e)
            rho, w = robust_weights(p_loss, jnp.sum(r**2, axis=-1))
            cost = cost + 0.5 * jnp.sum(rho)
            parts.append((e, r, None if p_loss is None else w))
        return cost, parts

    def _cost(self, poses, data, idx):
        return self._residuals(poses, data, idx)[0]

    def _system(self, poses, parts, data, idx):
        """`(diag, off, g)` of the normal equations from `_residuals`' parts, fixed poses
        masked."""
        st = self.static
        n, d, p = st["n"], st["d"], st["p"]
        _, root, _, prior = data
        relative, e, r, w = parts[0]
        # whitened blocks: R J_j = A and R J_i = -B with B = A Ad(H^{-1}) (as J_i = -J_j Ad), so
        # H_ii = BᵀWB, H_jj = AᵀWA, H_ij = -BᵀWA, g_i = -BᵀWr, g_j = AᵀWr. (One product of
        # [B | A | r] with itself would give them all, but XLA's CPU dot is several times slower
        # on those 13 columns than on three 6 × 6 products.)
        adjoint = relative.inverse().adjoint()
        if st["exact"]:
            A = root @ type(relative).right_jacobian_inverse(e)
        else:
            A = jnp.broadcast_to(root, adjoint.shape)
        B = A @ adjoint
        Jt = lambda a: jnp.swapaxes(a, -1, -2)
        WB, WA = (B, A) if w is None else (w[:, None, None] * B, w[:, None, None] * A)
        block_i = jnp.concatenate([Jt(WB) @ B, -jnp.einsum("kba,kb->ka", WB, r)[..., None]], -1)
        block_j = jnp.concatenate([Jt(WA) @ A, jnp.einsum("kba,kb->ka", WA, r)[..., None]], -1)
        seg = jax.ops.segment_sum
        both = seg(jnp.concatenate([block_i, block_j]), idx["ij"], n)  # [H | g] per pose
        diag, grad = both[..., :d], both[..., d]
        H_ij = -(Jt(WB) @ A)
        oriented = jnp.where(idx["flipped"][:, None, None], Jt(H_ij), H_ij)
        off = seg(oriented, idx["pair"], p)
        if prior is not None:
            p_root = prior[1]
            e, r, w = parts[1]
            J = p_root @ prior_jacobian_at(type(poses), e, st["exact"])
            wJ = J if w is None else w[:, None, None] * J
            diag = diag + seg(Jt(wJ) @ J, idx["prior"], n)
            grad = grad + seg(jnp.einsum("kba,kb->ka", wJ, r), idx["prior"], n)
        free = idx["free"]
        eye = jnp.eye(d, dtype=diag.dtype)
        diag = jnp.where(free[:, None, None], diag, eye)
        grad = jnp.where(free[:, None], grad, 0.0)
        off = jnp.where(idx["free_pair"][:, None, None], off, 0.0)
        return diag, off, grad

    def _linearize(self, poses, data, idx):
        """`(cost, diag, off, g)` of the normal equations at `poses`, fixed poses masked."""
        cost, parts = self._residuals(poses, data, idx)
        return (cost, *self._system(poses, parts, data, idx))

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
        """The Levenberg-Marquardt loop: one `while_loop` step per attempted damping. A step's
        cost evaluation (`_residuals`) is kept, and when the step is taken and the loop goes on,
        the normal equations are completed from it (`_system`, inside a `cond`): a rejected step
        costs one cost evaluation and no linearization. `params` is the vector of
        `_PARAMETERS`; returns the poses and one vector
        `[cost, lambda, iterations, solves, status, *history]`."""
        params = dict(zip(_PARAMETERS, params))
        params["max_iterations"] = params["max_iterations"].astype(jnp.int32)
        st = self.static
        group = type(poses)
        dtype = poses.dtype
        d = st["d"]
        eye = jnp.eye(d, dtype=dtype)
        cost, parts = self._residuals(poses, data, idx)
        history = jnp.full((st["history_size"],), jnp.nan, dtype).at[0].set(cost)
        status = jnp.where(
            jnp.isfinite(cost),
            jnp.where(params["max_iterations"] > 0, Status.RUNNING, Status.MAX_ITERATIONS),
            Status.NONFINITE,
        ).astype(jnp.int32)
        zero = jnp.zeros((), jnp.int32)
        system = self._system(poses, parts, data, idx)
        state = (
            poses.parameters(),
            cost,
            system,
            params["lambda_initial"],
            zero,
            zero,
            status,
            history,
        )

        def cond(state):
            return state[6] == Status.RUNNING

        def body(state):
            x, cost, system, lam, iterations, solves, status, history = state
            diag, off, grad = system
            finite = jnp.all(jnp.isfinite(diag)) & jnp.all(jnp.isfinite(grad))
            delta = self._solve(diag + lam * eye, off, -grad, params)
            solved = finite & jnp.all(jnp.isfinite(delta))
            delta = jnp.where(solved, delta, 0.0)
            # predicted decrease of the undamped model: -g.δ - ½ δ.Hδ, with Hδ = -g - λδ
            predicted = -0.5 * jnp.vdot(grad, delta) + 0.5 * lam * jnp.vdot(delta, delta)
            moved = st["retraction"].rplus(group._wrap(x), delta)
            candidate = group._wrap(group._normalize(moved.parameters()))
            new_cost, parts = self._residuals(candidate, data, idx)
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
            system = lax.cond(
                success & (status == Status.RUNNING),
                lambda: self._system(candidate, parts, data, idx),
                lambda: system,
            )
            return (x, next_cost, system, lam, iterations, solves + 1, status, history)

        x, cost, _, lam, iterations, solves, status, history = lax.while_loop(cond, body, state)
        scalars = jnp.stack([cost, lam, *(a.astype(dtype) for a in (iterations, solves, status))])
        return x, jnp.concatenate([scalars, history])
