r"""Point-to-point and point-to-plane ICP: one jitted loop, fixed shapes, batchable with `vmap`.

Conventions: `transform` is `T_target_source` (it maps source coordinates into the target frame),
a `lieax.SE3` with right perturbation $T \oplus \xi = T\,\mathrm{Exp}(\xi)$, tangent
$\xi = (v, \omega)$ translation first (docs/conventions.md).

The loop is Open3D's `registration_icp`: match every source point to its nearest target point,
reject pairs farther than `max_correspondence_distance` (masked, never dropped), update the pose
from the matched pairs, match again, and stop when neither the fitness nor the inlier RMSE changed
by more than its tolerance (Open3D's absolute changes), or after `max_iterations` updates. One
addition: the test also passes against the iteration before the last, so that a pose cycling
between two states (each update switching the matches that lead back) stops as converged.

- Point-to-plane: one Gauss-Newton step per iteration on $r_i = n_i^\top (T s_i - d_i)$, whose
  $1 \times 6$ Jacobian block $n_i^\top [R, -R[s_i]_\times]$ is written out per coordinate
  (`_plane_rows`, checked against `lieax.jacobian` of `SE3`'s action); the $6 \times 6$ normal
  equations are a reduction over the cloud, weighted by the robust loss (iteratively reweighted
  least squares).
- Point-to-point: the closed-form weighted Kabsch / Umeyama step (Arun et al. 1987), as Open3D.

Matching uses `search` (`lieax.icp._search`; default `"auto"`: the host k-d tree on CPUs,
warm-started and exact every iteration). With `search="graph"` it is a warm-started descent on the
target's neighbour graph (see `lieax.icp._neighbors`); when the stopping test passes, the matches
are recomputed exactly (within `max_correspondence_distance`), and the loop resumes if that
changed the fitness or RMSE (unless two exact checks in a row agree), so the result is the one
exact nearest neighbours give.

Presampling (`point_to_plane`, default `presample=0.125`): every 8th source point is registered
first, to looser tolerances, and the whole source from there: the iterations in which the pose
still slides (every match changes, so the host k-d tree's warm start keeps none) then query an
eighth of the points. The first stage runs on every 8th row alone (a strided slice), so that its
passes over the arrays cost an eighth too: masking the other rows of the full arrays, as before,
made the first stage on the benchmark's LiDAR pair 2.0x and on its Kinect pair 1.9x slower. Both
stages run in one compiled program (one preamble, one index); the converged pose is the full
registration's.

Shapes: by default (`buckets=True`) the clouds are padded (masked rows) to capacity buckets,
the next size of the form $c \cdot 2^k$, $c \in \{5, 6, 7, 8\}$ (`lieax.icp._batch.bucket_size`:
at most 25% padded rows, four shapes per doubling), and the results sliced back: a stream of
clouds of varying sizes (LiDAR odometry) compiles the loop and the normals once per bucket, not
once per size, with the results of the unpadded call.

Placement: the loop works on the source about its centroid and the target about its own, the
pose conjugated to match (`lieax.icp._centring`), so that clouds far from the origin
(georeferenced scans, 1e4-1e6 m away) register as they do at the origin: the same pose relative to
the clouds, the same iterations and status, up to the rounding of the coordinates themselves
(float64: 1e-10 m at 1e6 m; float32: a few ulps of the coordinates, up to 5 mm at 1e4 m and 2 cm
at 1e5 m, see `tests/test_icp_invariance.py`).

Derivatives: the loop runs on constants; `transform` and `inlier_rmse` get the implicit
derivative of the converged pose (`lieax.icp._implicit`).
"""

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np
from jax.scipy.linalg import cho_solve

from .. import _cpu_emitters as cpu_emitters
from .._checks import is_concrete, to_device
from .._linalg import quat_to_matrix
from .._runtime_error import raise_if
from ..groups import SE3, kernels
from ..lstsq._solution import SolverResult, Status, is_failure
from . import _host_kdtree, _neighbors, _search
from ._batch import chunked_on_cpu, pad_to_bucket
from ._centring import centred_pose, centroid
from ._checks import (
    ICPError,
    ICPInputError,
    check_cloud,
    check_count,
    check_mask,
    check_parameter,
    check_same_length,
)
from ._coordinates import row_sums, squared_norms
from ._implicit import estimated_normals, with_implicit_derivatives
from ._robust import loss_weights as _weights
from ._robust import split_loss as _split_loss

MIN_CORRESPONDENCES = 6
_IDENTITY = (1.0, 0.0, 0.0, 0.0, 0.0, 0.0, 0.0)
_DESCENT_STEPS = 2
# `point_to_plane(presample=...)`: the first registration's tolerances (the fitness's; the RMSE's
# in units of max_correspondence_distance), the fewest points it runs on, and the smallest
# `max_iterations` it runs for (a caller asking for a few iterations steps the whole source).
_PRESAMPLE_TOLERANCE = 1e-4
_PRESAMPLE_MIN_POINTS = 500
_PRESAMPLE_MIN_ITERATIONS = 10
_DEFAULT_PRESAMPLE = 0.125


class _ICPResultFields(NamedTuple):
    transform: SE3
    fitness: jax.Array
    inlier_rmse: jax.Array
    iterations: jax.Array
    status: jax.Array
    correspondences: jax.Array


class ICPResult(SolverResult, _ICPResultFields):
    """The result of `point_to_point` / `point_to_plane` / `gicp`, a pytree (it batches under
    `vmap`); a `lieax.lstsq.SolverResult`.

    **Fields:**

    - `transform`: `SE3`, `T_target_source`, mapping source coordinates into the target frame.
    - `fitness`: fraction of (valid) source points with a target point within
      `max_correspondence_distance` at `transform`.
    - `inlier_rmse`: root mean square distance of those pairs (0 when there are none).
    - `iterations`: pose updates made.
    - `status`: an integer `Status` code (`lieax.icp.Status`, which is `lieax.lstsq.Status`);
      `status_name` reads it. For ICP: `CONVERGED`, fitness and inlier RMSE changed by less
      than their tolerances; `MAX_ITERATIONS`, `max_iterations` updates ran; `NONFINITE`, a
      valid point, target normal, covariance or `init` is NaN or infinite (`transform` is
      `init`, `iterations` 0); `DEGENERATE`, fewer than 6 pairs within
      `max_correspondence_distance` or an update not finite (`transform` is the last pose
      reached); `INVALID`, a traced parameter out of range (`transform` is `init`,
      `iterations` 0).
    - `correspondences`: `(n,)` int32, index of each source point's match in the target, `-1`
      where it has none (rejected, or masked out).
    """

    __slots__ = ()
    _repr_fields = ("fitness", "inlier_rmse", "iterations")


class _State(NamedTuple):
    params: jax.Array
    slot: jax.Array
    d2: jax.Array
    fitness: jax.Array
    rmse: jax.Array
    count: jax.Array  # the inliers among the matches `d2` (carried: a pass less per iteration)
    iterations: jax.Array
    status: jax.Array
    checked_fitness: jax.Array  # the statistics of the last exact check (-1 before the first)
    checked_rmse: jax.Array
    earlier_fitness: jax.Array  # the statistics one iteration before the last
    earlier_rmse: jax.Array
    warm: object = None  # search="kdtree": the KDTreeWarmStart of the last match


# ---- public entry points ------------------------------------------------------------------------


def point_to_plane(
    source,
    target,
    *,
    max_correspondence_distance,
    target_normals=None,
    init=None,
    max_iterations=30,
    relative_fitness=1e-6,
    relative_rmse=1e-6,
    loss=None,
    source_mask=None,
    target_mask=None,
    exact=True,
    normals_k=30,
    verbose=False,
    throw=True,
    search="auto",
    buckets=True,
    presample=_DEFAULT_PRESAMPLE,
) -> ICPResult:
    r"""Point-to-plane ICP: minimize $\sum_i \rho\big((n_i^\top (T s_i - d_i))^2\big)$ over
    $T$ = `T_target_source`, re-matching $d_i$ (nearest target point of $T s_i$) every iteration.

    **Arguments:**

    - `source`, `target`: clouds of shape `(n, 3)` and `(m, 3)`, the same floating dtype.
    - `max_correspondence_distance`: pairs farther apart are rejected (masked); positive and
      finite (a concrete one that is not raises `ICPInputError`; a traced one ends `INVALID`).
    - `target_normals`: `(m, 3)` unit normals; default `estimate_normals(target, k=normals_k)`.
    - `init`: initial `SE3` guess of `T_target_source` (default identity).
    - `max_iterations`: most pose updates (an integer, NumPy's too).
    - `relative_fitness`, `relative_rmse`: stop when both changed by less than this in one
      iteration (Open3D's criteria: absolute changes of the fitness and of the RMSE); finite and
      non-negative (0 runs `max_iterations` updates unless the pose stops moving exactly).
    - `loss`: robust loss with a `weight(s)` method of the squared residual `s` (the
      `lieax.lstsq` losses: `Huber`, `Cauchy`, `Tukey`, `GemanMcClure`); default least squares.
    - `source_mask`, `target_mask`: `(n,)`, `(m,)` bools, False for padding (see `pad_clouds`).
    - `exact`: verify the final matches with an exact search (see the module docstring).
    - `normals_k`: neighbours for the default normals.
    - `verbose`: print the fitness and inlier RMSE after every iteration, from inside the compiled
      loop (`jax.debug.print`; under `vmap` one line per problem).
    - `throw`: raise `ICPError` (`ICPInputError` for bad input) when the run ends `NONFINITE`,
      `INVALID` or `DEGENERATE`: at once outside `jit`; under `jit` when the compiled program
      runs (a `JaxRuntimeError` carrying the `ICPError`'s message, through
      `lieax._runtime_error.raise_if`); under `vmap` never (read the per-problem `status`).
    - `search`: the correspondence search, `"auto"`, `"graph"`, `"grid"`, `"kdtree"` or
      `"brute"` (see `lieax.icp._search`), or an index prebuilt on `target` (and `target_mask`)
      by `build_index`, to reuse across calls (a `"grid"` one with a cell of at least
      `max_correspondence_distance`).
    - `buckets`: pad `source` and `target` (masked) to capacity buckets, so that clouds of new
      sizes reuse a compiled loop (see `bucket_size`: four sizes per doubling, at most 25%
      padded rows); `False` compiles for the exact shapes. The results are those of the
      unpadded call (`correspondences` has `n` entries and indexes the unpadded target).
    - `presample`: register every $k$-th source point first, $k$ = `round(1 / presample)`, to
      looser tolerances (1e-4 for the fitness, 1e-4 `max_correspondence_distance` for the RMSE,
      or the given ones if looser), then the whole source from that pose to the given criteria;
      0 (or a source of fewer than 500 $k$ points, `max_iterations` below 10, or
      `search="graph"`) registers the whole source from `init` directly. The first iterations, where the pose still slides and every
      match changes (the host k-d tree's warm start keeps none), then work on a $k$-th of the
      points; the result is the full registration's, converged from closer. Both stages run in
      one compiled program (0 runs the default's, its first stage skipped). Each stage is capped
      at `max_iterations`; `iterations` counts the pose updates of both.

    **Returns:** an `ICPResult`; `transform` and `inlier_rmse` are differentiable (forward and
    reverse mode) with respect to `source`, `target`, `target_normals` (given, or estimated from
    the target) and the loss's scale at a converged run, by the implicit function theorem (see
    `lieax.icp._implicit`: the matches are held fixed, the derivative with respect to `init` is
    zero; differentiating a run that did not converge raises `ICPError` outside `jit`/`vmap`,
    and gives NaN tangents inside or with `throw=False`).
    """
    return _register(
        "plane", source, target, max_correspondence_distance, target_normals, init,
        max_iterations, relative_fitness, relative_rmse, loss, source_mask, target_mask,
        exact, normals_k, verbose, throw, search=search, buckets=buckets,
        presample=presample,
    )  # fmt: skip


def point_to_point(
    source,
    target,
    *,
    max_correspondence_distance,
    init=None,
    max_iterations=30,
    relative_fitness=1e-6,
    relative_rmse=1e-6,
    loss=None,
    source_mask=None,
    target_mask=None,
    exact=True,
    verbose=False,
    throw=True,
    search="auto",
    buckets=True,
) -> ICPResult:
    r"""Point-to-point ICP: minimize $\sum_i \rho(\|T s_i - d_i\|^2)$ over $T$ = `T_target_source`
    with the closed-form (weighted Kabsch) step each iteration, re-matching $d_i$.

    Arguments as `point_to_plane` (no normals). **Returns:** an `ICPResult`.
    """
    return _register(
        "point", source, target, max_correspondence_distance, None, init, max_iterations,
        relative_fitness, relative_rmse, loss, source_mask, target_mask, exact, 0, verbose,
        throw, search=search, buckets=buckets,
    )  # fmt: skip


# ---- argument handling --------------------------------------------------------------------------


def _register(
    kind, source, target, max_distance, target_normals, init, max_iterations, relative_fitness,
    relative_rmse, loss, source_mask, target_mask, exact, normals_k, verbose, throw,
    search="graph", source_covariances=None, target_covariances=None, buckets=True,
    step_tolerance=None, presample=None,
):  # fmt: skip
    source = check_cloud(source, "source")
    target = check_cloud(target, "target")
    if source.dtype != target.dtype:
        raise TypeError(
            f"source and target must share a dtype, got {source.dtype} and {target.dtype}."
        )
    source_mask = check_mask(source_mask, source, "source_mask")
    target_mask = check_mask(target_mask, target, "target_mask")
    if kind == "plane" and target_normals is not None:
        target_normals = check_cloud(target_normals, "target_normals")
        check_same_length(target_normals, target, "target_normals", "target")
    n = source.shape[0]
    if buckets:
        source, source_mask, source_covariances = pad_to_bucket(
            source, source_mask, source_covariances
        )
        if isinstance(search, str):  # (an index prebuilt on the target fixes its rows)
            target, target_mask, target_normals, target_covariances = pad_to_bucket(
                target, target_mask, target_normals, target_covariances
            )
    if kind == "plane":
        if target_normals is None:
            target_normals = estimated_normals(target, target_mask, normals_k)
    else:
        target_normals = None
    if init is not None and (not isinstance(init, SE3) or init.batch_shape != ()):
        raise TypeError(f"init must be a single lieax.SE3 (use vmap for batches), got {init!r}.")
    init_params = None if init is None else init.parameters()
    max_iterations = check_count(max_iterations, "max_iterations")
    check_parameter(max_distance, "max_correspondence_distance", positive=True)
    check_parameter(relative_fitness, "relative_fitness", positive=False)
    check_parameter(relative_rmse, "relative_rmse", positive=False)
    if step_tolerance is not None:  # (rotation, translation): see `_small_step`
        check_parameter(step_tolerance[0], "rotation_epsilon", positive=False)
        check_parameter(step_tolerance[1], "translation_epsilon", positive=False)
        step_tolerance = _constant(_array_of(tuple(step_tolerance), source.dtype))

    search, prebuilt = _search.check_icp_search(search, target, max_distance)
    dynamic_loss, static_loss = _split_loss(loss)
    loss_kind = None if dynamic_loss is None else dynamic_loss[0]  # (static: one loop per kind)
    stride, presampled = _presample_plan(presample, n, search, max_iterations)
    options = (
        kind, max_iterations, bool(exact), _DESCENT_STEPS, bool(verbose), search, loss_kind,
        stride,
    )  # fmt: skip
    if loss is not None and dynamic_loss is not None:
        check_parameter(dynamic_loss[1], f"the scale of {type(loss).__name__}", positive=True)
    # The loop sees constants; the derivatives come from the implicit function theorem.
    data = (source, target, target_normals, (source_covariances, target_covariances))
    constant = jax.tree.map(_constant, (data, init_params, max_distance, dynamic_loss))
    (source_c, target_c, normals_c, covariances_c), init_c, max_distance_c, loss_c = constant
    loss_scale_c = None if loss_c is None else loss_c[1]
    dtype = source.dtype
    fitness_c, rmse_c = (_array_of(_constant(x), dtype) for x in (relative_fitness, relative_rmse))
    init_c = _array_of(_IDENTITY, dtype) if init_c is None else init_c
    result = _solve(
        source_c, source_mask, target_c, target_mask, normals_c, init_c, max_distance_c,
        fitness_c, rmse_c, loss_scale_c, _array_of(presampled), prebuilt, *covariances_c,
        step_tolerance, options=options, static_loss=static_loss,
    )  # fmt: skip
    if any(isinstance(x, jax.core.Tracer) for x in jax.tree.leaves((data, dynamic_loss))):
        loss_kind, loss_scale = (None, 0.0) if dynamic_loss is None else dynamic_loss
        result = with_implicit_derivatives(
            kind, static_loss, bool(throw), result,
            (source, target, target_normals, jnp.asarray(loss_scale, source.dtype), data[3]),
            (source_mask, loss_kind),
        )  # fmt: skip
    result = result._replace(correspondences=_first_rows(result.correspondences, n))
    return _raise_on_failure(result, max_distance) if throw else result


def _presample_plan(presample, n, search, max_iterations):
    """`(stride, run)` for the presampled first registration (`point_to_plane(presample=...)`).
    The stride shapes the compiled loop (static); `run` is passed traced, so that `presample=0`
    runs the loop compiled for the default with its first stage skipped (a caller switching
    presampling off compiles nothing new). Stride 1 (no first stage compiled) for `presample`
    above 1/2 and for `None` (the other ICP kinds), for sources of fewer than
    `_PRESAMPLE_MIN_POINTS` presampled points, for `max_iterations` below
    `_PRESAMPLE_MIN_ITERATIONS` (one call, one update for a caller stepping ICP by hand), and for
    `search="graph"` (not measured with its descent)."""
    if presample is None:
        return 1, False
    if isinstance(presample, bool) or not isinstance(presample, (int, float, np.floating)):
        raise ICPInputError(f"presample must be a number in [0, 1], got {presample!r}.")
    if not 0 <= presample <= 1:
        raise ICPInputError(f"presample must be a number in [0, 1], got {presample!r}.")
    if search == "graph" or max_iterations < _PRESAMPLE_MIN_ITERATIONS:
        return 1, False
    stride = max(1, round(1 / (presample or _DEFAULT_PRESAMPLE)))
    if stride == 1 or n // stride < _PRESAMPLE_MIN_POINTS:
        return 1, False
    return stride, presample > 0


def _raise_on_failure(result, max_distance):
    """`result`, after raising the `ICPError` its status calls for (`is_failure`): now when the
    status is concrete, when the compiled program runs under `jit` (`raise_if`), never under
    `vmap` (the statuses are the report)."""
    if isinstance(result.status, jax.core.Tracer):
        if isinstance(max_distance, jax.core.Tracer):
            max_distance = None
        traced = lambda code: _icp_error(code, max_distance, " (raised from inside jit)")
        return result._replace(status=raise_if(result.status, is_failure, traced))
    code = int(result.status)
    if is_failure(code):
        raise _icp_error(code, max_distance)
    return result


def _icp_error(code, max_distance, where=""):
    """The `ICPError` of a failure status `code`: `ICPInputError` for `NONFINITE` and `INVALID`
    (the input is at fault). `max_distance` is named when it is known (not None or traced)."""
    if code == Status.NONFINITE:
        return ICPInputError(
            f"ICP input is not finite{where}: a valid source or target point, a target normal, a "
            "covariance or init holds NaN or inf (mask such rows out, or pass throw=False)."
        )
    if code == Status.INVALID:
        return ICPInputError(
            f"ICP parameter out of range{where}: max_correspondence_distance or the loss's scale "
            "is not positive and finite, or a tolerance is negative or not finite (or pass "
            "throw=False)."
        )
    known = max_distance is not None and not isinstance(max_distance, jax.core.Tracer)
    distance = f"={float(max_distance):g}" if known else ""
    return ICPError(
        f"ICP is degenerate{where}: fewer than {MIN_CORRESPONDENCES} source points had a target "
        f"point within max_correspondence_distance{distance} (or the update was singular); "
        "check the initial guess and the distance, or pass throw=False."
    )


def _first_rows(array, n):
    """`array[:n]`, by NumPy for a concrete array (a slice per new size would compile)."""
    if n == array.shape[0]:
        return array
    if isinstance(array, jax.core.Tracer):
        return array[:n]
    return to_device(np.asarray(array)[:n])


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


def _array_of(values, dtype=None):
    """`values` (a number, an array, or a tuple of numbers or scalars) as one array of `dtype`
    (default its own): one transfer when concrete (`lieax._checks.to_device`), where
    `jnp.asarray` and `jnp.stack` would compile a small program per shape and dtype on first
    use (issue 30), else staged."""
    if is_concrete(values):
        return to_device(np.asarray(values, dtype))
    if isinstance(values, tuple):
        return jnp.stack([jnp.asarray(x, dtype) for x in values])
    return jnp.asarray(values, dtype)


def _constant(x):
    """`x` without derivatives (traced values only: concrete ones have none to stop)."""
    return jax.lax.stop_gradient(x) if isinstance(x, jax.core.Tracer) else x


# ---- the jitted loop ----------------------------------------------------------------------------


@cpu_emitters.jit(static_argnames=("options", "static_loss"))
def _solve(*arrays, options, static_loss):
    """`_loop` of the arrays `(source, source_mask, target, target_mask, target_normals, init,
    max_distance, relative_fitness, relative_rmse, loss, presampled, index, source_covariances,
    target_covariances, step_tolerance)`, all positional: under `vmap` on a CPU it runs in
    chunks (`chunked_on_cpu`). Compiled once per shape and static option; the `vmap` rule sits
    inside the compiled function, so that a call outside `vmap` runs this compiled program."""

    def one(*arrays):
        *arrays, index, source_covariances, target_covariances, step_tolerance = arrays
        return _loop(
            *arrays, options=options, static_loss=static_loss, index=index,
            source_covariances=source_covariances, target_covariances=target_covariances,
            step_tolerance=step_tolerance,
        )  # fmt: skip

    return chunked_on_cpu(one, arrays[0].shape[0])(*arrays)


def _loop(
    source, source_mask, target, target_mask, target_normals, init, max_distance,
    relative_fitness, relative_rmse, loss, presampled, *, options, static_loss, index=None,
    source_covariances=None, target_covariances=None, step_tolerance=None,
):  # fmt: skip
    kind, max_iterations, exact, steps, verbose, search, loss_kind, stride = options
    loss = None if loss is None else (loss_kind, loss)  # (the kind static, the scale traced)
    dtype = source.dtype
    if target_normals is None:
        target_normals = jnp.zeros_like(target)
    target_normals = target_normals.astype(dtype)
    init = init.astype(dtype)
    max_distance, relative_fitness, relative_rmse = (
        jnp.asarray(x).astype(dtype) for x in (max_distance, relative_fitness, relative_rmse)
    )

    def weights(squared):
        return _weights(loss, static_loss, squared)

    # Finite rows, and one reduction per cloud for "a valid row is not finite" (a float sum: XLA's
    # CPU backend splits a boolean or integer reduction into three kernels).
    source_rows = jnp.all(jnp.isfinite(source), axis=1)
    target_rows = jnp.all(jnp.isfinite(target), axis=1)
    target_bad = ~(target_rows & jnp.all(jnp.isfinite(target_normals), axis=1))
    source_bad = ~source_rows
    if kind == "gicp":  # (n, 3, 3) and (m, 3, 3) covariances, checked by lieax.icp.gicp
        source_bad = source_bad | ~jnp.all(jnp.isfinite(source_covariances), axis=(1, 2))
        target_bad = target_bad | ~jnp.all(jnp.isfinite(target_covariances), axis=(1, 2))
    init_finite = jnp.all(jnp.isfinite(init))
    finite = (_count(source_mask & source_bad) == 0) & (_count(target_mask & target_bad) == 0)
    finite = finite & init_finite
    # Parameters traced under jit / vmap (concrete ones were checked by `_register`).
    valid = _positive(max_distance) & _non_negative(relative_fitness)
    valid = valid & _non_negative(relative_rmse)
    if step_tolerance is not None:
        valid = valid & jnp.all(_non_negative(step_tolerance))
    if loss is not None:
        valid = valid & _positive(jnp.asarray(loss[1]).astype(dtype))
    # (Under vmap the loop's body also runs for an INVALID problem, its results discarded: the
    # searches need a radius they accept.)
    max_distance = jnp.where(_positive(max_distance), max_distance, 1.0)
    source_mask = source_mask & source_rows
    target_mask = target_mask & target_rows
    source = jnp.where(source_mask[:, None], source, 0.0)
    target = jnp.where(target_mask[:, None], target, 0.0)
    start = jnp.where(init_finite, init, jnp.asarray(_IDENTITY, dtype))

    # The loop runs on the source about its centroid and the target about its own, the pose
    # conjugated to match (`lieax.icp._centring`): the result does not depend on where the clouds
    # sit. The index keeps the target as given (its host tree, and a prebuilt index, are those of
    # the user's points): queries reach it shifted back, distances are recomputed centred.
    target_centre = centroid(target, target_mask)
    if index is None:
        index = _search.build_index(target, target_mask, search=search, max_distance=max_distance)
    target_points = index.points - target_centre.astype(index.points.dtype)
    normals = jnp.where(index.valid[:, None], target_normals[index.order], 0.0)
    if kind == "gicp":
        eye = jnp.eye(3, dtype=dtype)
        target_covariances = jnp.where(
            index.valid[:, None, None], target_covariances.astype(dtype)[index.order], eye
        )
    r2 = max_distance * max_distance
    start_status = jnp.where(
        valid, jnp.where(finite, Status.RUNNING, Status.NONFINITE), Status.INVALID
    ).astype(jnp.int32)
    finite = finite & valid

    def register(
        source, source_mask, source_covariances, start, relative_fitness, relative_rmse, status
    ):
        """Register the rows `source_mask` of `source` from the pose `start` (not if `status`
        is not `RUNNING`): the last `_State` (about the centroids), the source's visiting order,
        centroid and mask in that order."""
        n = source.shape[0]
        source_centre = centroid(source, source_mask)
        source = jnp.where(source_mask[:, None], source - source_centre, 0.0)
        start = centred_pose(start, source_centre, target_centre)
        # Visit the source in a space-filling-curve order: consecutive queries then read nearby
        # rows of the target's tables (its slots are in k-d tree order), which keeps the gathers
        # in cache.
        order = _neighbors.spatial_order(source, source_mask)
        source, source_mask = source[order], source_mask[order]
        if kind == "gicp":
            source_covariances = source_covariances.astype(dtype)[order]
        n_valid = jnp.maximum(_count(source_mask), 1)

        def moved(params):
            return jnp.where(source_mask[:, None], transform_points(params, source), 0.0)

        def in_index(queries):
            """Centred queries in the index's frame (the target's, as given)."""
            return queries + target_centre

        def centred(queries, slot, found):
            """The squared distances of the matches `found` by the index, recomputed in the
            centred frame (`inf` where it found none)."""
            gap = queries - target_points[slot].astype(dtype)
            return jnp.where(found, squared_norms(gap), jnp.inf)

        def statistics(d2):
            return _statistics(d2, source_mask, n_valid, r2)

        def update(params, slot, inliers):
            matched = target_points[slot]
            if kind == "plane":
                return _plane_step(params, source, matched, normals[slot], inliers, weights)
            if kind == "gicp":
                from ._gicp import gicp_step  # (a module that imports this one)

                return gicp_step(
                    params, source, matched, source_covariances, target_covariances[slot],
                    inliers, weights,
                )  # fmt: skip
            return _point_step(params, source, matched, inliers, weights)

        def inner_step(state):
            """Update the pose from the current matches, then match again. The very first pass
            (the matches are not there yet) only matches, at `init`."""
            first = state.iterations < 0
            inliers = (state.d2 <= r2) & source_mask
            enough = state.count >= MIN_CORRESPONDENCES
            candidate = update(state.params, state.slot, inliers)
            ok = enough & jnp.all(jnp.isfinite(candidate))
            params = jnp.where(ok & ~first, candidate, state.params)
            queries = moved(params)
            warm = state.warm
            if search == "graph":
                slot, d2, _ = _neighbors.track(
                    index, in_index(queries), state.slot, max_steps=steps, mask=source_mask
                )
                found = jnp.isfinite(d2)
            elif search == "kdtree":  # exact; the host sees only queries whose match may change
                slot, _, warm = _host_kdtree.track_in_kdtree(
                    index, in_index(queries), max_distance, state.warm,
                    mask=source_mask & (state.status == Status.RUNNING),
                )  # fmt: skip
                # Matches within twice the radius; the statistics test the centred distances
                # against the radius. (The tree's distances, in the index's frame, go unused:
                # XLA drops their gather, a pass over the rows per iteration.)
                found = warm.slot >= 0
            else:  # exact in every iteration
                slot, d2 = _search.match(index, in_index(queries), max_distance, source_mask)
                found = jnp.isfinite(d2)
            d2 = jnp.where(source_mask, centred(queries, slot, found), jnp.inf)
            _, fitness, rmse, count = statistics(d2)
            iterations = state.iterations + (ok | first).astype(jnp.int32)

            def unchanged(f, r):
                return (jnp.abs(fitness - f) < relative_fitness) & (
                    jnp.abs(rmse - r) < relative_rmse
                )

            # Open3D's test, and the same against the iteration before: with the matches
            # switching back and forth, the pose can cycle between two states that each update
            # leads to the other; Open3D would run to max_iterations there.
            converged = unchanged(state.fitness, state.rmse) | unchanged(
                state.earlier_fitness, state.earlier_rmse
            )
            if step_tolerance is not None:
                converged = converged | _small_step(
                    state.params, params, source_centre, step_tolerance
                )
            status = jnp.where(
                ~(ok | first),
                Status.DEGENERATE,
                jnp.where(
                    converged & ~first,
                    Status.CONVERGED,
                    jnp.where(iterations >= max_iterations, Status.MAX_ITERATIONS, Status.RUNNING),
                ),
            )
            if verbose:
                jax.debug.print(
                    "icp iteration {i:3d}: fitness {f:.6f}, inlier RMSE {r:.6g}",
                    i=iterations, f=fitness, r=rmse,
                )  # fmt: skip
            keep = lambda new, old: jnp.where(ok | first, new, old)
            return state._replace(
                params=params, slot=keep(slot, state.slot), d2=keep(d2, state.d2),
                fitness=keep(fitness, state.fitness), rmse=keep(rmse, state.rmse),
                count=keep(count, state.count), iterations=iterations,
                status=status.astype(jnp.int32),
                earlier_fitness=keep(state.fitness, state.earlier_fitness),
                earlier_rmse=keep(state.rmse, state.earlier_rmse), warm=warm,
            )  # fmt: skip

        def running(state):
            return state.status == Status.RUNNING

        def verified(state):
            """Iterate, then check the matches exactly. Resume if that changed the statistics,
            unless they also equal those of the previous check: the pose has settled, and what
            differs is a few matches that the warm-started descent keeps missing."""
            state = jax.lax.while_loop(running, inner_step, state)
            if not exact or search != "graph":
                return state
            queries = moved(state.params)
            certified = _neighbors.certify(index, state.slot, state.d2, max_distance) | ~source_mask
            slot, d2, _ = _neighbors.refine_uncertified(
                index, in_index(queries), state.slot, state.d2, certified, max_distance, scan=False
            )
            d2 = jnp.where(source_mask, centred(queries, slot, jnp.isfinite(d2)), jnp.inf)
            _, fitness, rmse, count = statistics(d2)

            def unchanged(f, r):
                return (jnp.abs(fitness - f) < relative_fitness) & (
                    jnp.abs(rmse - r) < relative_rmse
                )

            settled = unchanged(state.fitness, state.rmse) | unchanged(
                state.checked_fitness, state.checked_rmse
            )
            resume = (
                (state.status == Status.CONVERGED) & ~settled & (state.iterations < max_iterations)
            )
            status = jnp.where(resume, Status.RUNNING, state.status).astype(jnp.int32)
            checked = state.status != Status.DEGENERATE
            keep = lambda new, old: jnp.where(checked, new, old)
            return state._replace(
                slot=keep(slot, state.slot), d2=keep(d2, state.d2),
                fitness=keep(fitness, state.fitness), rmse=keep(rmse, state.rmse),
                count=keep(count, state.count), status=status, checked_fitness=fitness,
                checked_rmse=rmse,
            )  # fmt: skip

        minus_one = jnp.asarray(-1.0, dtype)
        no_count = jnp.zeros((), jnp.result_type(float))
        state = _State(
            start, jnp.zeros((n,), jnp.int32), jnp.full((n,), jnp.inf, dtype), minus_one,
            minus_one, no_count, jnp.asarray(-1, jnp.int32), status, minus_one, minus_one,
            minus_one, minus_one,
        )  # fmt: skip
        if search == "kdtree":
            state = state._replace(warm=_host_kdtree.cold_start(n, dtype))
        if exact and search == "graph":  # (only the graph's exact check can resume the loop)
            state = jax.lax.while_loop(running, verified, state)
        else:
            state = verified(state)
        return state, order, source_centre, source_mask

    presampled_iterations = 0
    if stride > 1:
        # Every stride-th source point first, to looser tolerances, on those rows alone: the
        # first iterations, where the pose slides and every match changes, then cost an eighth
        # (`point_to_plane(presample=...)`). Skipped (INVALID: not usable) unless `presampled`.
        loose = jnp.asarray(_PRESAMPLE_TOLERANCE, dtype)
        sampled_covariances = None if kind != "gicp" else source_covariances[::stride]
        first, _, first_centre, _ = register(
            source[::stride], source_mask[::stride], sampled_covariances, start,
            jnp.maximum(relative_fitness, loose), jnp.maximum(relative_rmse, loose * max_distance),
            jnp.where(presampled, start_status, Status.INVALID).astype(jnp.int32),
        )  # fmt: skip
        usable = (first.status == Status.CONVERGED) | (first.status == Status.MAX_ITERATIONS)
        reached = centred_pose(first.params, -first_centre, -target_centre)
        start = jnp.where(usable, reached, start)
        presampled_iterations = jnp.where(usable, jnp.maximum(first.iterations, 0), 0)

    state, order, source_centre, source_mask = register(
        source, source_mask, source_covariances, start, relative_fitness, relative_rmse,
        start_status,
    )  # fmt: skip
    n_valid = jnp.maximum(_count(source_mask), 1)
    inliers, _, _, _ = _statistics(state.d2, source_mask, n_valid, r2)
    correspondences = jnp.where(inliers, index.order[state.slot], -1)
    correspondences = jnp.zeros_like(correspondences).at[order].set(correspondences)
    params = jnp.where(finite, centred_pose(state.params, -source_centre, -target_centre), init)
    zero = jnp.zeros((), dtype)
    return ICPResult(
        kernels.element(SE3, params),
        jnp.where(finite, state.fitness, zero),
        jnp.where(finite, state.rmse, zero),
        jnp.maximum(state.iterations, 0) + presampled_iterations,
        state.status,
        correspondences,
    )


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


# ---- one update ---------------------------------------------------------------------------------


def transform_points(params, points):
    """$R p + t$ for SE3 parameters `(w, x, y, z, tx, ty, tz)` and points `(n, 3)`, written out per
    coordinate: `SE3.act`'s values (its contraction agrees with float64 in float32 at 20k points,
    `tests/test_icp_invariance.py`), 1.5-7x faster on 20k points on the CPU and 7-10x under
    `vmap` (jaxlib 0.10.2, float64 and float32)."""
    return jnp.stack(_transformed_columns(params, points), axis=1)


def _transformed_columns(params, points):
    """The three coordinates of `transform_points(params, points)`, each `(n,)` (a step that
    reduces over them needs no `(n, 3)` array)."""
    rotation = quat_to_matrix(params[:4])
    x, y, z = points[:, 0], points[:, 1], points[:, 2]
    return [
        rotation[i, 0] * x + rotation[i, 1] * y + rotation[i, 2] * z + params[4 + i]
        for i in range(3)
    ]


def _plane_rows(params, points, normals):
    r"""$J_i = \partial\, n_i^\top (T \oplus \xi)\, s_i / \partial \xi
    = n_i^\top [R, -R[s_i]_\times] = [m_i^\top, (s_i \times m_i)^\top]$, $m_i = R^\top n_i$,
    for SE3 parameters `params`, transposed: `(6, n)`, column $i$ is $J_i$. The action's Jacobian
    $[R, -R[s]_\times]$ (Solà, Deray, Atchuthan 2018, "A micro Lie theory", appendix D, right
    perturbation) and $-m^\top [s]_\times = (s \times m)^\top$. Written out per coordinate: one
    fused kernel, where `lieax.jacobian` of the action under `vmap` compiles to eight on the CPU;
    six contiguous rows, where `(n, 6)` rows cost a strided concatenation and a transpose for the
    reduction (the step 1.5-2x slower at 160k points).
    `tests/test_icp.py` checks it against `lieax.jacobian` and finite differences."""
    rotation = quat_to_matrix(params[:4])
    m = [sum(rotation[a, j] * normals[:, a] for a in range(3)) for j in range(3)]
    s = [points[:, k] for k in range(3)]
    cross = [s[1] * m[2] - s[2] * m[1], s[2] * m[0] - s[0] * m[2], s[0] * m[1] - s[1] * m[0]]
    return jnp.stack(m + cross, axis=0)


def _plane_step(params, source, matched, normals, inliers, loss_weights):
    r"""One Gauss-Newton step $T \leftarrow T \oplus \delta$, $\delta = -(J^\top W J)^{-1} J^\top W r$,
    with rows $J_i = n_i^\top [R, -R[s_i]_\times]$ (see `_plane_rows`). The 21 distinct entries
    of $J^\top W J$ and the 6 of $J^\top W r$ are one reduction over the rows (`row_sums`): no
    `(6, n)` array is written, where the matrix products of the weighted rows had two. Five
    steps with their gathers, float64: 13 ms against 29 at 160k rows, 0.66 against 0.79 ms at
    10k, half the temporary memory (jaxlib 0.10.2, CPU)."""
    pose = kernels.element(SE3, params)
    moved = _transformed_columns(params, source)
    residuals = sum(normals[:, a] * (moved[a] - matched[:, a]) for a in range(3))
    weights = inliers.astype(params.dtype) * loss_weights(residuals * residuals)
    rows = list(_plane_rows(params, source, normals))
    weighted = [row * weights for row in rows]
    upper = [(i, j) for i in range(6) for j in range(i, 6)]
    sums = row_sums(
        [weighted[i] * rows[j] for i, j in upper] + [row * residuals for row in weighted]
    )
    entries = dict(zip(upper, sums))
    hessian = jnp.stack(
        [jnp.stack([entries[min(i, j), max(i, j)] for j in range(6)]) for i in range(6)]
    )
    gradient = jnp.stack(sums[len(upper) :])
    step = -_solve_spd(hessian, gradient)
    return pose.rplus(step).parameters()


def _solve_spd(matrix, rhs):
    r"""$(H + \lambda I)^{-1} b$ by Cholesky, $\lambda = 10\,n\,\varepsilon \max_i H_{ii}$: a ridge at
    rounding level, so that a rank-deficient $H$ (a plane slides along itself) still gives a
    finite step with no component along its null space. Fixed points ($b = 0$) are unchanged."""
    n = matrix.shape[-1]
    scale = jnp.max(jnp.abs(jnp.diagonal(matrix)))
    ridge = 10 * n * jnp.finfo(matrix.dtype).eps * jnp.maximum(scale, jnp.finfo(matrix.dtype).tiny)
    factor = jnp.linalg.cholesky(matrix + ridge * jnp.eye(n, dtype=matrix.dtype))
    return cho_solve((factor, True), rhs)


def _point_step(params, source, matched, inliers, loss_weights):
    r"""The rigid motion that best maps the moved source onto its matches (weighted Kabsch),
    composed on the left: $T \leftarrow \Delta T \cdot T$."""
    moved = transform_points(params, source)
    weights = inliers.astype(params.dtype) * loss_weights(squared_norms(moved - matched))
    total = jnp.maximum(jnp.sum(weights), jnp.finfo(params.dtype).tiny)
    mean_moved = jnp.sum(weights[:, None] * moved, axis=0) / total
    mean_matched = jnp.sum(weights[:, None] * matched, axis=0) / total
    covariance = jnp.einsum(
        "n,ni,nj->ij", weights, matched - mean_matched, moved - mean_moved,
        precision=jax.lax.Precision.HIGHEST,
    )  # fmt: skip
    u, _, vt = jnp.linalg.svd(covariance)
    sign = jnp.sign(jnp.linalg.det(u @ vt))
    sign = jnp.where(sign == 0, 1.0, sign)
    rotation = (
        u * jnp.array([1.0, 1.0, 0.0], params.dtype)
        + u * jnp.array([0.0, 0.0, 1.0], params.dtype) * sign
    ) @ vt
    translation = mean_matched - rotation @ mean_moved
    delta = SE3.from_matrix(
        jnp.concatenate(
            [
                jnp.concatenate([rotation, translation[:, None]], axis=1),
                jnp.array([[0.0, 0.0, 0.0, 1.0]], params.dtype),
            ],
            axis=0,
        )
    )
    return (delta @ kernels.element(SE3, params)).parameters()
