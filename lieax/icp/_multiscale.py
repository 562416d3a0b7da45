"""Coarse-to-fine ICP on a voxel pyramid (Open3D's `registration.multi_scale_icp`).

Each level downsamples both clouds on its voxel grid, estimates the normals (point-to-plane) or
covariances (GICP) of the downsampled clouds, and registers them from the pose the previous level
reached, with its own `max_correspondence_distance` and iteration cap. Coarse levels see the
overall shape with a wide capture distance; fine levels refine on the full detail.
"""

import math
from collections.abc import Iterable
from typing import Any, Literal, overload

import jax
import jax.numpy as jnp
import numpy as np
from jax.typing import ArrayLike

from ..groups import SE3, kernels
from ._checks import ICPInputError, check_cloud, check_count, check_mask
from ._downsample import voxel_downsample
from ._gicp import gicp
from ._registration import (
    ICPError,
    ICPResult,
    Status,
    _raise_on_failure,
    point_to_plane,
    point_to_point,
)
from ._robust import WeightedLoss

_METHODS = {"point_to_point": point_to_point, "point_to_plane": point_to_plane, "gicp": gicp}


@overload
def multi_scale(
    source: ArrayLike,
    target: ArrayLike,
    *,
    voxel_sizes: Iterable[ArrayLike | None],
    max_correspondence_distances: Iterable[ArrayLike],
    max_iterations: int | np.integer | Iterable[int | np.integer] = 30,
    method: str = "point_to_plane",
    init: SE3 | None = None,
    loss: WeightedLoss | None = None,
    source_mask: ArrayLike | None = None,
    target_mask: ArrayLike | None = None,
    return_levels: Literal[False] = False,
    throw: bool = True,
    **options: Any,
) -> ICPResult: ...
@overload
def multi_scale(
    source: ArrayLike,
    target: ArrayLike,
    *,
    voxel_sizes: Iterable[ArrayLike | None],
    max_correspondence_distances: Iterable[ArrayLike],
    max_iterations: int | np.integer | Iterable[int | np.integer] = 30,
    method: str = "point_to_plane",
    init: SE3 | None = None,
    loss: WeightedLoss | None = None,
    source_mask: ArrayLike | None = None,
    target_mask: ArrayLike | None = None,
    return_levels: Literal[True],
    throw: bool = True,
    **options: Any,
) -> tuple[ICPResult, list[ICPResult]]: ...
@overload
def multi_scale(
    source: ArrayLike,
    target: ArrayLike,
    *,
    voxel_sizes: Iterable[ArrayLike | None],
    max_correspondence_distances: Iterable[ArrayLike],
    max_iterations: int | np.integer | Iterable[int | np.integer] = 30,
    method: str = "point_to_plane",
    init: SE3 | None = None,
    loss: WeightedLoss | None = None,
    source_mask: ArrayLike | None = None,
    target_mask: ArrayLike | None = None,
    return_levels: bool,
    throw: bool = True,
    **options: Any,
) -> ICPResult | tuple[ICPResult, list[ICPResult]]: ...
def multi_scale(
    source,
    target,
    *,
    voxel_sizes,
    max_correspondence_distances,
    max_iterations=30,
    method="point_to_plane",
    init=None,
    loss=None,
    source_mask=None,
    target_mask=None,
    return_levels=False,
    throw=True,
    **options,
):
    """Register `source` to `target` level by level, coarse to fine.

    **Arguments:**

    - `source`, `target`: clouds of shape `(n, 3)` and `(m, 3)`.
    - `voxel_sizes`: one voxel side per level, coarse first (decreasing); `None` for a level on
      the clouds as given.
    - `max_correspondence_distances`: one per level (e.g. 1.5 to 3 voxel sides).
    - `max_iterations`: an int for every level, or one per level.
    - `method`: `"point_to_plane"`, `"gicp"` or `"point_to_point"`.
    - `init`: initial `SE3` guess of `T_target_source` for the first level (default identity).
    - `loss`, `source_mask`, `target_mask`: as for the method, at every level.
    - `return_levels`: also return the result of every level.
    - `throw`: raise `ICPError` when the finest level ends `NONFINITE`, `INVALID` or `DEGENERATE`
      (under `jit` when the program runs, as the methods; never under `vmap`); a coarse level
      that fails hands its last pose on. A valid input point that is not finite makes the result
      `NONFINITE` (with `init`), whatever the levels (whose voxels drop such points) reached.
    - `options`: further keyword arguments of the method (`relative_fitness`, `normals_k`,
      `covariances_k`, ...), the same at every level.

    Called eagerly, each level's clouds are the occupied voxels' centroids, padded (masked) to a
    power-of-two row count shared by both clouds (fewer compilations). Under `jit` or
    `vmap` the shapes cannot depend on the data: every level keeps the input's row count, with the
    voxels' centroids first and the rest masked out (correct, but coarse levels then cost as much
    as fine ones).

    **Returns:** the `ICPResult` of the finest level (its `correspondences` index that level's
    downsampled clouds), or `(result, per_level_results)` with `return_levels=True`.
    """
    if method not in _METHODS:
        raise ValueError(f"method must be one of {sorted(_METHODS)}, got {method!r}.")
    register = _METHODS[method]
    source = check_cloud(source, "source")
    target = check_cloud(target, "target")
    source_mask = check_mask(source_mask, source, "source_mask")
    target_mask = check_mask(target_mask, target, "target_mask")
    voxel_sizes = tuple(voxel_sizes)
    distances = tuple(max_correspondence_distances)
    levels = len(voxel_sizes)
    if levels == 0:
        raise ValueError("voxel_sizes must name at least one level.")
    if isinstance(max_iterations, (int, np.integer)):
        max_iterations = (max_iterations,) * levels
    iterations = tuple(check_count(cap, "max_iterations") for cap in max_iterations)
    if len(distances) != levels or len(iterations) != levels:
        raise ValueError(
            f"voxel_sizes ({levels} levels), max_correspondence_distances ({len(distances)}) and "
            f"max_iterations ({len(iterations)}) must have one entry per level."
        )
    concrete = not any(
        isinstance(x, jax.core.Tracer) for x in (source, target, source_mask, target_mask)
    )
    results = []
    pose = init
    for voxel, distance, cap in zip(voxel_sizes, distances, iterations):
        s, sm, t, tm = _level(source, source_mask, target, target_mask, voxel, concrete)
        result = register(
            s, t, max_correspondence_distance=distance, init=pose, max_iterations=cap, loss=loss,
            source_mask=sm, target_mask=tm, throw=False, **options,
        )  # fmt: skip
        results.append(result)
        pose = result.transform
    finite = _finite(source, source_mask) & _finite(target, target_mask)
    result = results[-1] = _unless_finite(finite, result, init)
    if throw and not concrete:  # under jit: raised when the program runs (never under vmap)
        result = results[-1] = _raise_on_failure(result, distances[-1])
    elif throw:
        status = Status(int(result.status))
        if status in (Status.NONFINITE, Status.INVALID, Status.DEGENERATE):
            error = ICPError if status == Status.DEGENERATE else ICPInputError
            raise error(
                f"multi-scale ICP ended {status.name} at its finest level (voxel size "
                f"{voxel_sizes[-1]}, max_correspondence_distance {distances[-1]}): check the "
                "inputs and the initial guess, or pass throw=False."
            )
    return (result, results) if return_levels else result


def _finite(points, mask):
    return jnp.all(jnp.isfinite(points) | ~mask[:, None])


def _unless_finite(finite, result, init):
    """`result`, or, where a valid input point is not finite (the voxel levels would drop it),
    the `NONFINITE` result of the methods: `init` (the identity by default), zero iterations,
    fitness and RMSE, no correspondences."""
    dtype = result.fitness.dtype
    start = (SE3.identity(dtype=dtype) if init is None else init).parameters().astype(dtype)
    keep = lambda new, old: jnp.where(finite, new, old)
    return result._replace(
        transform=kernels.element(SE3, keep(result.transform.parameters(), start)),
        fitness=keep(result.fitness, 0.0).astype(dtype),
        inlier_rmse=keep(result.inlier_rmse, 0.0).astype(dtype),
        iterations=keep(result.iterations, 0),
        status=keep(result.status, Status.NONFINITE).astype(result.status.dtype),
        correspondences=keep(result.correspondences, -1),
    )


def _level(source, source_mask, target, target_mask, voxel, concrete):
    """The clouds of one level: voxel centroids, or the clouds themselves for `voxel=None`. With
    concrete data both are padded (masked) to one power-of-two row count, so that repeated calls
    and both clouds reuse compiled code; traced data keeps the input's row counts."""
    if voxel is None:
        return source, source_mask, target, target_mask
    if not concrete:
        s, sm = voxel_downsample(source, voxel, mask=source_mask, size=source.shape[0])
        t, tm = voxel_downsample(target, voxel, mask=target_mask, size=target.shape[0])
        return s, sm, t, tm
    s = voxel_downsample(source, voxel, mask=source_mask)
    t = voxel_downsample(target, voxel, mask=target_mask)
    rows = 2 ** math.ceil(math.log2(max(s.shape[0], t.shape[0])))
    return (*_padded(s, rows), *_padded(t, rows))


def _padded(points, rows):
    mask = np.arange(rows) < points.shape[0]
    return jnp.pad(points, ((0, rows - points.shape[0]), (0, 0))), jnp.asarray(mask)
