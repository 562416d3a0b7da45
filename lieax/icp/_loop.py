r"""The ICP loop, a template handed its parts (`lieax.icp._parts`): a `Step` that updates the pose
from matched pairs (point-to-point, point-to-plane, GICP) and a `Matcher` that finds the pairs (a
k-d tree, a grid, brute force). It knows neither by name: the entry points choose them
(small_gicp's `Registration`, Koide, small_gicp, `registration/registration.hpp`).

The loop is Open3D's `registration_icp`: match every source point to its nearest target point,
reject pairs farther than `max_correspondence_distance` (masked, never dropped), update the pose
from the matched pairs, match again, and stop when neither the fitness nor the inlier RMSE changed
by more than its tolerance (Open3D's absolute changes), or after `max_iterations` updates. One
addition: the test also passes against the iteration before the last, so that a pose cycling
between two states (each update switching the matches that lead back) stops as converged. With a
step tolerance (GICP), it also stops on a small update (`_small_step`, small_gicp's rule).

Presampling (stride $k > 1$): every $k$-th source row is registered first, to looser tolerances,
on those rows alone (a strided slice: its passes cost a $k$-th), and the whole source from the
pose it reached; both stages in one compiled program (one index).

Placement: the loop works on the source about its centroid and the target about its own, the
pose conjugated to match (`lieax.icp._centring`); the index keeps the target as given (queries
reach it shifted back, distances are recomputed centred).
"""

from typing import NamedTuple

import jax
import jax.numpy as jnp

from .. import _cpu_emitters as cpu_emitters
from .._linalg import quat_to_matrix
from ..groups import SE3, kernels
from ..lstsq._solution import Status
from ._batch import chunked_on_cpu
from ._centring import centred_pose, centroid
from ._coordinates import row_sums, squared_norms, transform_points
from ._robust import loss_weights
from ._spatial_order import spatial_order

MIN_CORRESPONDENCES = 6
IDENTITY = (1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
# The first stage's tolerances when presampling: the fitness's, and the RMSE's in units of
# max_correspondence_distance. Where the first stage stops decides where on the whole cloud's
# (often flat, in planar scenes) valley the full stage starts; which tolerance lands closest is
# chance from start to start. Over 16 starts on each Kinect pair (December 2026, issue 31's note)
# 1e-4 and 3e-4 took the same time within 2% overall and 1e-3 up to 30% more on some rows; from
# the identity, 1e-4 left the full stage of the Kinect 1 cm pair 31 iterations of sliding at
# 1e-10 / 60 where 3e-4 left 6.
PRESAMPLE_TOLERANCE = 3e-4


class Options(NamedTuple):
    """The static options of the compiled loop: its parts and the shapes of its work."""

    step: object  # lieax.icp._parts.Step
    matcher: object  # lieax.icp._parts.Matcher
    max_iterations: int
    verbose: bool
    loss_kind: object  # the kind of a lieax.lstsq loss (its scale is traced), or None
    stride: int  # presampling stride, 1 for none


class _State(NamedTuple):
    params: jax.Array
    slot: jax.Array
    d2: jax.Array
    fitness: jax.Array
    rmse: jax.Array
    count: jax.Array  # the inliers among the matches `d2` (carried: a pass less per iteration)
    iterations: jax.Array
    status: jax.Array
    earlier_fitness: jax.Array  # the statistics one iteration before the last
    earlier_rmse: jax.Array
    carry: object  # the matcher's own state


class _Target(NamedTuple):
    """The target side, shared by the stages: its index, points about its centroid and the
    step's rows in the index's slot order (zero in invalid slots)."""

    index: object
    points: jax.Array
    rows: object
    centre: jax.Array
    max_distance: jax.Array
    r2: jax.Array


class _Stage(NamedTuple):
    """One registration's source side, about its centroid, in its visiting order."""

    source: jax.Array
    mask: jax.Array
    rows: object
    centre: jax.Array
    n_valid: jax.Array
    relative_fitness: jax.Array
    relative_rmse: jax.Array


@cpu_emitters.jit(static_argnames=("options", "static_loss"))
def solve(*arrays, options, static_loss):
    """`loop` of the arrays `(source, source_mask, target, target_mask, source_rows, target_rows,
    init, max_distance, relative_fitness, relative_rmse, loss, presampled, index,
    step_tolerance)`, all positional: under `vmap` on a CPU it runs in chunks (`chunked_on_cpu`).
    Compiled once per shape and static option; the `vmap` rule sits inside the compiled function,
    so that a call outside `vmap` runs this compiled program."""

    def one(*arrays):
        return loop(*arrays, options=options, static_loss=static_loss)

    return chunked_on_cpu(one, arrays[0].shape[0])(*arrays)


def loop(
    source, source_mask, target, target_mask, source_rows, target_rows, init, max_distance,
    relative_fitness, relative_rmse, loss, presampled, index, step_tolerance, *, options,
    static_loss,
):  # fmt: skip
    """Register `source` to `target` (see the module docstring). **Returns:** `(params, fitness,
    inlier_rmse, iterations, status, correspondences)`."""
    dtype = source.dtype
    init = init.astype(dtype)
    max_distance, relative_fitness, relative_rmse = (
        jnp.asarray(x).astype(dtype) for x in (max_distance, relative_fitness, relative_rmse)
    )
    source_rows, target_rows = jax.tree.map(lambda x: x.astype(dtype), (source_rows, target_rows))
    # (the loss's kind static, its scale traced)
    loss = None if loss is None else (options.loss_kind, loss)
    source_ok = _finite_rows(source, source_rows)
    target_ok = _finite_rows(target, target_rows)
    init_finite = jnp.all(jnp.isfinite(init))
    finite = (_count(source_mask & ~source_ok) == 0) & (_count(target_mask & ~target_ok) == 0)
    finite = finite & init_finite
    valid = _valid(max_distance, relative_fitness, relative_rmse, step_tolerance, loss, dtype)
    # (Under vmap the loop's body also runs for an INVALID problem, its results discarded: the
    # searches need a radius they accept.)
    max_distance = jnp.where(_positive(max_distance), max_distance, 1.0)
    source_mask = source_mask & jnp.all(jnp.isfinite(source), axis=1)
    target_mask = target_mask & jnp.all(jnp.isfinite(target), axis=1)
    source = jnp.where(source_mask[:, None], source, 0.0)
    target = jnp.where(target_mask[:, None], target, 0.0)
    start = jnp.where(init_finite, init, jnp.asarray(IDENTITY, dtype))
    if index is None:
        index = options.matcher.build(target, target_mask, max_distance)
    goal = _target(index, target, target_mask, target_rows, max_distance)
    start_status = jnp.where(
        valid, jnp.where(finite, Status.RUNNING, Status.NONFINITE), Status.INVALID
    ).astype(jnp.int32)
    finite = finite & valid
    run = lambda *args: _register(options, static_loss, loss, goal, step_tolerance, *args)

    presampled_iterations = 0
    stride = options.stride
    if stride > 1:
        # Every stride-th source point first, to looser tolerances, on those rows alone; skipped
        # (INVALID: not usable) unless `presampled`.
        loose = jnp.asarray(PRESAMPLE_TOLERANCE, dtype)
        sampled_rows = jax.tree.map(lambda x: x[::stride], source_rows)
        first, first_centre = run(
            source[::stride], source_mask[::stride], sampled_rows, start,
            jnp.maximum(relative_fitness, loose), jnp.maximum(relative_rmse, loose * max_distance),
            jnp.where(presampled, start_status, Status.INVALID).astype(jnp.int32),
        )[:2]  # fmt: skip
        usable = (first.status == Status.CONVERGED) | (first.status == Status.MAX_ITERATIONS)
        reached = centred_pose(first.params, -first_centre, -goal.centre)
        start = jnp.where(usable, reached, start)
        presampled_iterations = jnp.where(usable, jnp.maximum(first.iterations, 0), 0)

    state, source_centre, stage, order = run(
        source, source_mask, source_rows, start, relative_fitness, relative_rmse, start_status
    )
    inliers, _, _, _ = _statistics(state.d2, stage.mask, stage.n_valid, goal.r2)
    correspondences = jnp.where(inliers, index.order[state.slot], -1)
    correspondences = jnp.zeros_like(correspondences).at[order].set(correspondences)
    params = jnp.where(finite, centred_pose(state.params, -source_centre, -goal.centre), init)
    zero = jnp.zeros((), dtype)
    return (
        params, jnp.where(finite, state.fitness, zero), jnp.where(finite, state.rmse, zero),
        jnp.maximum(state.iterations, 0) + presampled_iterations, state.status, correspondences,
    )  # fmt: skip


def _target(index, target, target_mask, target_rows, max_distance):
    """The `_Target` of an index built on `target` (as given)."""
    centre = centroid(target, target_mask)
    points = index.points - centre.astype(index.points.dtype)

    def in_slots(rows):
        blank = index.valid.reshape(index.valid.shape + (1,) * (rows.ndim - 1))
        return jnp.where(blank, rows[index.order], 0.0)

    rows = jax.tree.map(in_slots, target_rows)
    return _Target(index, points, rows, centre, max_distance, max_distance * max_distance)


def _register(
    options, static_loss, loss, goal, step_tolerance, source, source_mask, source_rows, start,
    relative_fitness, relative_rmse, status,
):  # fmt: skip
    """Register the rows `source_mask` of `source` from the pose `start` (not if `status` is not
    `RUNNING`). **Returns:** the last `_State` (about the centroids), the source's centroid, the
    `_Stage` and the visiting order."""
    n, dtype = source.shape[0], source.dtype
    source_centre = centroid(source, source_mask)
    source = jnp.where(source_mask[:, None], source - source_centre, 0.0)
    start = centred_pose(start, source_centre, goal.centre)
    # Visit the source in a space-filling-curve order: consecutive queries then read nearby rows
    # of the target's tables (its slots are in k-d tree order), which keeps the gathers in cache.
    order = spatial_order(source, source_mask)
    source, source_mask = source[order], source_mask[order]
    source_rows = jax.tree.map(lambda x: x[order], source_rows)
    n_valid = jnp.maximum(_count(source_mask), 1)
    stage = _Stage(
        source, source_mask, source_rows, source_centre, n_valid, relative_fitness, relative_rmse
    )
    minus_one = jnp.asarray(-1.0, dtype)
    no_count = jnp.zeros((), jnp.result_type(float))
    state = _State(
        start, jnp.zeros((n,), jnp.int32), jnp.full((n,), jnp.inf, dtype), minus_one, minus_one,
        no_count, jnp.asarray(-1, jnp.int32), status, minus_one, minus_one,
        options.matcher.start(n, dtype),
    )  # fmt: skip
    weights = lambda squared: loss_weights(loss, static_loss, squared)
    iterate = lambda state: _iteration(options, weights, goal, stage, step_tolerance, state)
    running = lambda state: state.status == Status.RUNNING
    return jax.lax.while_loop(running, iterate, state), source_centre, stage, order


def _iteration(options, weights, goal, stage, step_tolerance, state):
    """Update the pose from the current matches, then match again. The very first pass (the
    matches are not there yet) only matches, at the start."""
    dtype = stage.source.dtype
    first = state.iterations < 0
    inliers = (state.d2 <= goal.r2) & stage.mask
    enough = state.count >= MIN_CORRESPONDENCES
    matched_rows = jax.tree.map(lambda rows: rows[state.slot], goal.rows)
    candidate = options.step.update(
        state.params, stage.source, stage.rows, goal.points[state.slot], matched_rows, inliers,
        weights,
    )  # fmt: skip
    ok = enough & jnp.all(jnp.isfinite(candidate))
    params = jnp.where(ok & ~first, candidate, state.params)
    queries = jnp.where(stage.mask[:, None], transform_points(params, stage.source), 0.0)
    active = stage.mask & (state.status == Status.RUNNING)
    slot, found, carry = options.matcher.match(
        goal.index, queries + goal.centre, goal.max_distance, active, state.carry
    )
    # The squared distances recomputed in the centred frame (`inf` where the index found none).
    gap = queries - goal.points[slot].astype(dtype)
    d2 = jnp.where(stage.mask & found, squared_norms(gap), jnp.inf)
    _, fitness, rmse, count = _statistics(d2, stage.mask, stage.n_valid, goal.r2)
    iterations = state.iterations + (ok | first).astype(jnp.int32)

    def unchanged(f, r):
        return (jnp.abs(fitness - f) < stage.relative_fitness) & (
            jnp.abs(rmse - r) < stage.relative_rmse
        )

    # Open3D's test, and the same against the iteration before: with the matches switching back
    # and forth, the pose can cycle between two states that each update leads to the other;
    # Open3D would run to max_iterations there.
    converged = unchanged(state.fitness, state.rmse) | unchanged(
        state.earlier_fitness, state.earlier_rmse
    )
    if step_tolerance is not None:
        converged = converged | _small_step(state.params, params, stage.centre, step_tolerance)
    status = jnp.where(
        ~(ok | first),
        Status.DEGENERATE,
        jnp.where(
            converged & ~first,
            Status.CONVERGED,
            jnp.where(iterations >= options.max_iterations, Status.MAX_ITERATIONS, Status.RUNNING),
        ),
    )
    if options.verbose:
        jax.debug.print(
            "icp iteration {i:3d}: fitness {f:.6f}, inlier RMSE {r:.6g}",
            i=iterations, f=fitness, r=rmse,
        )  # fmt: skip
    keep = lambda new, old: jnp.where(ok | first, new, old)
    return state._replace(
        params=params, slot=keep(slot, state.slot), d2=keep(d2, state.d2),
        fitness=keep(fitness, state.fitness), rmse=keep(rmse, state.rmse),
        count=keep(count, state.count), iterations=iterations, status=status.astype(jnp.int32),
        earlier_fitness=keep(state.fitness, state.earlier_fitness),
        earlier_rmse=keep(state.rmse, state.earlier_rmse), carry=carry,
    )  # fmt: skip


def _statistics(d2, source_mask, n_valid, r2):
    """The inliers (`(n,)` bools), fitness, inlier RMSE and inlier count of the squared match
    distances `d2` (one reduction for both sums: no `(n,)` float array of the flags is written,
    a pass and 1.3 MB less at 160k rows)."""
    dtype = d2.dtype
    inliers = (d2 <= r2) & source_mask
    wide = jnp.result_type(float)  # (one precision for both sums: float64 under x64)
    count, total = row_sums([inliers.astype(wide), jnp.where(inliers, d2, 0.0).astype(wide)])
    fitness = count / n_valid
    rmse = jnp.sqrt(total / jnp.maximum(count, 1).astype(dtype))
    rmse = jnp.where(count > 0, rmse, 0.0).astype(dtype)
    return inliers, fitness.astype(dtype), rmse, count


def _finite_rows(points, rows):
    """Whether each row of `points` and of the step's `rows` (a pytree of arrays with the same
    number of rows, or None) is finite."""
    ok = jnp.all(jnp.isfinite(points), axis=1)
    for leaf in jax.tree.leaves(rows):
        ok = ok & jnp.all(jnp.isfinite(leaf.reshape(leaf.shape[0], -1)), axis=1)
    return ok


def _valid(max_distance, relative_fitness, relative_rmse, step_tolerance, loss, dtype):
    """Whether the parameters (traced under jit / vmap; concrete ones were checked already) are in
    range."""
    valid = _positive(max_distance) & _non_negative(relative_fitness)
    valid = valid & _non_negative(relative_rmse)
    if step_tolerance is not None:
        valid = valid & jnp.all(_non_negative(step_tolerance))
    if loss is not None:
        valid = valid & _positive(jnp.asarray(loss[1]).astype(dtype))
    return valid


def _count(flags):
    """The number of True entries of `flags`, as a float (exact: float64 under x64, float32
    below 2**24 rows): XLA's CPU backend compiles an integer or boolean reduction as three
    kernels, a float one as one."""
    return jnp.sum(flags.astype(jnp.result_type(float)))


def _small_step(params, updated, source_centre, tolerance):
    r"""Whether the update from the centred pose `params` to `updated` moved by less than
    `tolerance` = (rotation, translation) in both parts. The update in the clouds' own frames is
    $D = T_\text{before}^{-1} T = \mathrm{Tr}(c_s)\,D_c\,\mathrm{Tr}(-c_s)$ for the centred poses'
    $D_c = (R_c, t_c)$ (`lieax.icp._centring`): rotation $R_c$ by the angle
    $2\,\mathrm{atan2}(\|q_{xyz}\|, |q_w|)$ of its quaternion, translation
    $t_c + (I - R_c)\,c_s$. small_gicp's `TerminationCriteria` (Koide, small_gicp,
    `registration/termination_criteria.hpp`) tests the parts of the tangent $\delta$,
    $D = \mathrm{Exp}(\delta)$: the same angle, and a translation within a factor
    $1 + O(\theta)$ of this one (no logarithm to compile here)."""
    step = (kernels.element(SE3, params).inverse() @ kernels.element(SE3, updated)).parameters()
    angle = 2 * jnp.arctan2(jnp.linalg.norm(step[1:4]), jnp.abs(step[0]))
    turned = jnp.matmul(
        quat_to_matrix(step[:4]), source_centre, precision=jax.lax.Precision.HIGHEST
    )
    translation = step[4:] + source_centre - turned
    return (angle < tolerance[0]) & (jnp.linalg.norm(translation) < tolerance[1])


def _positive(x):
    return jnp.isfinite(x) & (x > 0)


def _non_negative(x):
    return jnp.isfinite(x) & (x >= 0)
