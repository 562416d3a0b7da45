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

- Point-to-plane: one Gauss-Newton step per iteration on $r_i = n_i^\top (T s_i - d_i)$
  (`lieax.icp._plane_step`), weighted by the robust loss (iteratively reweighted least squares).
- Point-to-point: the closed-form weighted Kabsch / Umeyama step (Arun et al. 1987), as Open3D
  (`lieax.icp._point_step`).

This module checks the arguments and hands the loop (`lieax.icp._loop`, a template that knows no
step or search by name) its parts: the step, and the matcher of `search` (`lieax.icp._search`;
default `"auto"`: the k-d tree on CPUs, warm-started and exact every iteration,
`lieax.icp._matchers`).

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
from jax.typing import ArrayLike

from .._checks import is_concrete, to_device
from .._runtime_error import raise_if
from ..groups import SE3, kernels
from ..lstsq._solution import SolverResult, Status, is_failure
from . import _search
from ._batch import pad_to_bucket
from ._checks import (
    ICPError,
    ICPInputError,
    check_cloud,
    check_count,
    check_mask,
    check_parameter,
    check_same_length,
)
from ._implicit import estimated_normals, with_implicit_derivatives
from ._loop import IDENTITY, MIN_CORRESPONDENCES, Options, solve
from ._matchers import matcher_for
from ._plane_step import POINT_TO_PLANE
from ._point_step import POINT_TO_POINT
from ._robust import WeightedLoss
from ._robust import split_loss as _split_loss
from ._search import NeighbourIndex

# `point_to_plane(presample=...)`: the fewest points the first registration runs on, and the
# smallest `max_iterations` it runs for (a caller asking for a few iterations steps the whole
# source); its tolerances are `lieax.icp._loop.PRESAMPLE_TOLERANCE`.
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


# ---- public entry points ------------------------------------------------------------------------


def point_to_plane(
    source: ArrayLike,
    target: ArrayLike,
    *,
    max_correspondence_distance: ArrayLike,
    target_normals: ArrayLike | None = None,
    init: SE3 | None = None,
    max_iterations: int | np.integer = 30,
    relative_fitness: ArrayLike = 1e-6,
    relative_rmse: ArrayLike = 1e-6,
    loss: WeightedLoss | None = None,
    source_mask: ArrayLike | None = None,
    target_mask: ArrayLike | None = None,
    normals_k: int | np.integer = 30,
    verbose: bool = False,
    throw: bool = True,
    search: str | NeighbourIndex = "auto",
    buckets: bool = True,
    presample: float = _DEFAULT_PRESAMPLE,
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
    - `normals_k`: neighbours for the default normals.
    - `verbose`: print the fitness and inlier RMSE after every iteration, from inside the compiled
      loop (`jax.debug.print`; under `vmap` one line per problem).
    - `throw`: raise `ICPError` (`ICPInputError` for bad input) when the run ends `NONFINITE`,
      `INVALID` or `DEGENERATE`: at once outside `jit`; under `jit` when the compiled program
      runs (a `JaxRuntimeError` carrying the `ICPError`'s message, through
      `lieax._runtime_error.raise_if`); under `vmap` never (read the per-problem `status`).
    - `search`: the correspondence search, `"auto"`, `"grid"`, `"kdtree"` or `"brute"` (see
      `lieax.icp._search`), or an index prebuilt on `target` (and `target_mask`)
      by `build_index`, to reuse across calls (a `"grid"` one with a cell of at least
      `max_correspondence_distance`).
    - `buckets`: pad `source` and `target` (masked) to capacity buckets, so that clouds of new
      sizes reuse a compiled loop (see `bucket_size`: four sizes per doubling, at most 25%
      padded rows); `False` compiles for the exact shapes. The results are those of the
      unpadded call (`correspondences` has `n` entries and indexes the unpadded target).
    - `presample`: register every $k$-th source point first, $k$ = `round(1 / presample)`, to
      looser tolerances (3e-4 for the fitness, 3e-4 `max_correspondence_distance` for the RMSE,
      or the given ones if looser), then the whole source from that pose to the given criteria;
      0 (or a source of fewer than 500 $k$ points, or `max_iterations` below 10) registers the
      whole source from `init` directly. The first iterations, where the pose still slides and every
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
    target = check_cloud(target, "target")
    if target_normals is not None:
        target_normals = check_cloud(target_normals, "target_normals")
        check_same_length(target_normals, target, "target_normals", "target")
    else:  # (estimated on the target as registered: padded to its bucket)
        target_normals = lambda target, mask: estimated_normals(target, mask, normals_k)
    return _register(
        POINT_TO_PLANE, source, target, max_correspondence_distance, init, max_iterations,
        relative_fitness, relative_rmse, loss, source_mask, target_mask, verbose, throw, search,
        buckets, target_rows=target_normals, presample=presample,
    )  # fmt: skip


def point_to_point(
    source: ArrayLike,
    target: ArrayLike,
    *,
    max_correspondence_distance: ArrayLike,
    init: SE3 | None = None,
    max_iterations: int | np.integer = 30,
    relative_fitness: ArrayLike = 1e-6,
    relative_rmse: ArrayLike = 1e-6,
    loss: WeightedLoss | None = None,
    source_mask: ArrayLike | None = None,
    target_mask: ArrayLike | None = None,
    verbose: bool = False,
    throw: bool = True,
    search: str | NeighbourIndex = "auto",
    buckets: bool = True,
) -> ICPResult:
    r"""Point-to-point ICP: minimize $\sum_i \rho(\|T s_i - d_i\|^2)$ over $T$ = `T_target_source`
    with the closed-form (weighted Kabsch) step each iteration, re-matching $d_i$.

    Arguments as `point_to_plane` (no normals). **Returns:** an `ICPResult`.
    """
    return _register(
        POINT_TO_POINT, source, target, max_correspondence_distance, init, max_iterations,
        relative_fitness, relative_rmse, loss, source_mask, target_mask, verbose, throw, search,
        buckets,
    )  # fmt: skip


# ---- argument handling --------------------------------------------------------------------------


def _register(
    step, source, target, max_distance, init, max_iterations, relative_fitness, relative_rmse,
    loss, source_mask, target_mask, verbose, throw, search, buckets, *, source_rows=None,
    target_rows=None, step_tolerance=None, presample=None,
):  # fmt: skip
    """Check the arguments, run the loop (`lieax.icp._loop`) with `step` (a
    `lieax.icp._parts.Step`) and the matcher of `search`, and attach the implicit derivatives.
    `source_rows`, `target_rows`: the step's per-point data (checked by the entry point), or a
    function `(target, target_mask)` that makes `target_rows` on the target as registered (padded
    to its bucket)."""
    source = check_cloud(source, "source")
    target = check_cloud(target, "target")
    if source.dtype != target.dtype:
        raise TypeError(
            f"source and target must share a dtype, got {source.dtype} and {target.dtype}."
        )
    source_mask = check_mask(source_mask, source, "source_mask")
    target_mask = check_mask(target_mask, target, "target_mask")
    n = source.shape[0]
    make_rows = target_rows if callable(target_rows) else None
    target_rows = None if make_rows else target_rows
    if buckets:
        source, source_mask, source_rows = pad_to_bucket(source, source_mask, source_rows)
        if isinstance(search, str):  # (an index prebuilt on the target fixes its rows)
            target, target_mask, target_rows = pad_to_bucket(target, target_mask, target_rows)
    if make_rows:
        target_rows = make_rows(target, target_mask)
    if init is not None and (not isinstance(init, SE3) or init.batch_shape != ()):
        raise TypeError(f"init must be a single lieax.SE3 (use vmap for batches), got {init!r}.")
    init_params = None if init is None else init.parameters()
    max_iterations = check_count(max_iterations, "max_iterations")
    check_parameter(max_distance, "max_correspondence_distance", positive=True)
    check_parameter(relative_fitness, "relative_fitness", positive=False)
    check_parameter(relative_rmse, "relative_rmse", positive=False)
    if step_tolerance is not None:  # (rotation, translation): see `_loop._small_step`
        check_parameter(step_tolerance[0], "rotation_epsilon", positive=False)
        check_parameter(step_tolerance[1], "translation_epsilon", positive=False)
        step_tolerance = _constant(_array_of(tuple(step_tolerance), source.dtype))

    search, prebuilt = _search.check_icp_search(search, target, max_distance)
    dynamic_loss, static_loss = _split_loss(loss)
    loss_kind = None if dynamic_loss is None else dynamic_loss[0]  # (static: one loop per kind)
    stride, presampled = _presample_plan(presample, n, max_iterations)
    options = Options(step, matcher_for(search), max_iterations, bool(verbose), loss_kind, stride)
    if loss is not None and dynamic_loss is not None:
        check_parameter(dynamic_loss[1], f"the scale of {type(loss).__name__}", positive=True)
    # The loop sees constants; the derivatives come from the implicit function theorem.
    data = (source, target, target_rows, source_rows)
    constant = jax.tree.map(_constant, (data, init_params, max_distance, dynamic_loss))
    (source_c, target_c, target_rows_c, source_rows_c), init_c, max_distance_c, loss_c = constant
    loss_scale_c = None if loss_c is None else loss_c[1]
    dtype = source.dtype
    fitness_c, rmse_c = (_array_of(_constant(x), dtype) for x in (relative_fitness, relative_rmse))
    init_c = _array_of(IDENTITY, dtype) if init_c is None else init_c
    params, *outputs = solve(
        source_c, source_mask, target_c, target_mask, source_rows_c, target_rows_c, init_c,
        max_distance_c, fitness_c, rmse_c, loss_scale_c, _array_of(presampled), prebuilt,
        step_tolerance, options=options, static_loss=static_loss,
    )  # fmt: skip
    result = ICPResult(kernels.element(SE3, params), *outputs)
    if any(isinstance(x, jax.core.Tracer) for x in jax.tree.leaves((data, dynamic_loss))):
        loss_kind, loss_scale = (None, 0.0) if dynamic_loss is None else dynamic_loss
        result = with_implicit_derivatives(
            step.name, static_loss, bool(throw), result,
            (source, target, target_rows, jnp.asarray(loss_scale, source.dtype), source_rows),
            (source_mask, loss_kind),
        )  # fmt: skip
    result = result._replace(correspondences=_first_rows(result.correspondences, n))
    return _raise_on_failure(result, max_distance) if throw else result


def _presample_plan(presample, n, max_iterations):
    """`(stride, run)` for the presampled first registration (`point_to_plane(presample=...)`).
    The stride shapes the compiled loop (static); `run` is passed traced, so that `presample=0`
    runs the loop compiled for the default with its first stage skipped (a caller switching
    presampling off compiles nothing new). Stride 1 (no first stage compiled) for `presample`
    above 1/2 and for `None` (the other ICP kinds), for sources of fewer than
    `_PRESAMPLE_MIN_POINTS` presampled points, for `max_iterations` below
    `_PRESAMPLE_MIN_ITERATIONS` (one call, one update for a caller stepping ICP by hand)."""
    if presample is None:
        return 1, False
    if isinstance(presample, bool) or not isinstance(presample, (int, float, np.floating)):
        raise ICPInputError(f"presample must be a number in [0, 1], got {presample!r}.")
    if not 0 <= presample <= 1:
        raise ICPInputError(f"presample must be a number in [0, 1], got {presample!r}.")
    if max_iterations < _PRESAMPLE_MIN_ITERATIONS:
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
