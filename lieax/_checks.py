"""Trace-time checks of shapes and dtypes, with errors that name what was expected."""

import jax.numpy as jnp
import numpy as np


def as_float_array(x, what: str) -> jnp.ndarray:
    """`x` as a JAX array with a floating dtype; `TypeError` naming `what` otherwise. A Python
    number (`0`, `1`) states no dtype and becomes the default float (float64 under x64)."""
    if isinstance(x, (int, float)) and not isinstance(x, bool):
        x = jnp.asarray(x, dtype=jnp.result_type(float))
    x = jnp.asarray(x)
    if not jnp.issubdtype(x.dtype, jnp.floating):
        raise TypeError(f"{what} must have a floating dtype (float32 or float64), got {x.dtype}.")
    return x


def check_last_axis(x, size: int, what: str, layout: str = "") -> jnp.ndarray:
    """`x` as a float array whose last axis has `size` entries; `ValueError` otherwise."""
    x = as_float_array(x, what)
    if x.ndim == 0 or x.shape[-1] != size:
        described = f" ({layout})" if layout else ""
        raise ValueError(
            f"{what} must have shape (*batch, {size}){described}, got shape {tuple(x.shape)}."
        )
    return x


def check_matrix(x, size: int, what: str) -> jnp.ndarray:
    """`x` as a float array of `size`×`size` matrices; `ValueError` otherwise."""
    x = as_float_array(x, what)
    if x.ndim < 2 or x.shape[-2:] != (size, size):
        raise ValueError(
            f"{what} must have shape (*batch, {size}, {size}), got shape {tuple(x.shape)}."
        )
    return x


def broadcast_batch(what: str, *shapes) -> tuple:
    """The broadcast of batch shapes, NumPy's rules; `ValueError` naming `what` otherwise."""
    try:
        return tuple(np.broadcast_shapes(*shapes))
    except ValueError:
        listed = " and ".join(str(tuple(s)) for s in shapes)
        raise ValueError(f"{what}: batch shapes {listed} do not broadcast.") from None
