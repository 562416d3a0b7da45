"""Trace-time checks of point clouds and masks, with errors that name the argument."""

import jax.numpy as jnp
import numpy as np

from .._checks import as_float_array


def check_cloud(points, what: str) -> jnp.ndarray:
    """`points` as a float array of shape `(n, 3)` with `n >= 1`; `ValueError` / `TypeError`
    naming `what` otherwise (shapes are static, so this raises under `jit` and `vmap` too)."""
    points = as_float_array(points, what)
    if points.ndim != 2 or points.shape[-1] != 3:
        raise ValueError(f"{what} must have shape (n, 3), got shape {tuple(points.shape)}.")
    if points.shape[0] == 0:
        raise ValueError(f"{what} is empty (shape {tuple(points.shape)}); ICP needs points.")
    return points


def check_mask(mask, points, what: str) -> jnp.ndarray:
    """A boolean mask of shape `(n,)` for `points` (all True when `mask` is None)."""
    if mask is None:
        return jnp.asarray(np.ones(points.shape[:1], bool))  # a host array: no device dispatch
    mask = jnp.asarray(mask)
    if mask.shape != points.shape[:1]:
        raise ValueError(
            f"{what} must have shape {tuple(points.shape[:1])} (one entry per point), "
            f"got shape {tuple(mask.shape)}."
        )
    return mask if mask.dtype == bool else mask.astype(bool)


def check_same_length(a, b, what_a: str, what_b: str):
    if a.shape != b.shape:
        raise ValueError(
            f"{what_a} must have the shape of {what_b}, {tuple(b.shape)}, got {tuple(a.shape)}."
        )
