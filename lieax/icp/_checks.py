"""Trace-time checks of point clouds, masks and parameters, with errors that name the argument;
the errors of `lieax.icp`."""

import operator

import jax
import jax.numpy as jnp
import numpy as np

from .._checks import as_float_array, to_device
from ..lstsq._solution import SolveError


class ICPError(SolveError):
    """The `lieax.lstsq.SolveError` of ICP (so also a `RuntimeError`): raised with `throw=True`
    when a run ends `NONFINITE`, `INVALID` or `DEGENERATE` (at once outside `jit`, when the
    compiled program runs inside it, never under `vmap`: read `status`), and when a run that
    did not converge is differentiated (its derivative is undefined)."""


class ICPInputError(ICPError, ValueError):
    """The `ICPError` of bad input: a concrete parameter out of range (raised when called), or,
    with `throw=True`, a run that ended `NONFINITE` or `INVALID`. Also a `ValueError`: the input
    is at fault."""


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
        return to_device(np.ones(points.shape[:1], bool))  # a transfer: nothing to compile
    mask = to_device(mask)
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


def check_count(value, what, minimum=0):
    """`value` as a Python int of at least `minimum` (NumPy integers too, by `operator.index`;
    not a bool); `ICPInputError` naming `what` otherwise."""
    try:
        count = None if isinstance(value, (bool, np.bool_)) else operator.index(value)
    except TypeError:
        count = None
    if count is None or count < minimum:
        raise ICPInputError(f"{what} must be an int of at least {minimum}, got {value!r}.")
    return count


def check_parameter(value, what, *, positive):
    """Raise `ICPInputError` naming `what` unless a concrete `value` (a Python number or a
    scalar array) is finite and positive (`positive`) or non-negative. A traced value is checked
    where it is used (ICP's loop ends `INVALID`)."""
    if isinstance(value, jax.core.Tracer):
        return
    array = np.asarray(value)
    if array.shape != () or not np.issubdtype(array.dtype, np.number) or np.iscomplexobj(array):
        raise ICPInputError(f"{what} must be a real number, got {value!r}.")
    number = float(array)
    if not np.isfinite(number) or (number <= 0 if positive else number < 0):
        raise ICPInputError(
            f"{what} must be {'positive' if positive else 'non-negative'} and finite, "
            f"got {number:g}."
        )
