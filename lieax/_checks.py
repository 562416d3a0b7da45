"""Trace-time checks of shapes and dtypes, with errors that name what was expected."""

import jax
import jax.numpy as jnp
import numpy as np


def foreign_conversion(x):
    """How to turn `x` into what lieax takes, when it is an object of a library lieax users come
    from, or `None`: a jaxlie group (its `parameters()` are lieax's parameters in the same
    order: wxyz / `(w, x, y, z, tx, ty, tz)` for SO3 / SE3, `(cos, sin)` / `(cos, sin, x, y)`
    for SO2 / SE2) or an Open3D point cloud (`np.asarray(cloud.points)`, an `(n, 3)` array)."""
    kind = type(x)
    module = kind.__module__ or ""
    if module.split(".")[0] == "jaxlie" and kind.__name__ in ("SO2", "SE2", "SO3", "SE3"):
        return f"a jaxlie.{kind.__name__}: convert it with lieax.{kind.__name__}(x.parameters())"
    if module.split(".")[0] == "open3d" and hasattr(x, "points"):
        return f"an Open3D {kind.__name__}: pass np.asarray(cloud.points) (an (n, 3) array)"
    return None


def check_not_foreign(x, what: str) -> None:
    """`TypeError` naming `what` and the conversion when `x` is a jaxlie group or an Open3D
    point cloud (`foreign_conversion`); JAX would fail on it with an error about dtype
    `object`, or take a jaxlie group for a plain array of its parameters."""
    conversion = foreign_conversion(x)
    if conversion is not None:
        raise TypeError(f"{what} is {conversion}.")


def is_concrete(*trees) -> bool:
    """Whether no leaf of `trees` is traced (by `jit`, `vmap`, `grad`, ...): concrete values can be
    worked on in NumPy, which compiles nothing (see `to_device`)."""
    return not any(isinstance(leaf, jax.core.Tracer) for leaf in jax.tree.leaves(trees))


def to_device(array) -> jax.Array:
    """A host array (or Python numbers) as a JAX array in JAX's dtype for it (float64 is float32
    without x64), by one transfer: `jnp.asarray` of a NumPy array compiles a small XLA program
    per shape and dtype on first use, and building a problem would wait on many of them
    (issue 30). JAX arrays and tracers are returned as they are."""
    if isinstance(array, jax.Array):
        return array
    array = np.asarray(array)
    return jax.device_put(array.astype(jax.dtypes.canonicalize_dtype(array.dtype), copy=False))


def as_float_array(x, what: str) -> jnp.ndarray:
    """`x` as a JAX array with a floating dtype; `TypeError` naming `what` otherwise (with the
    conversion, for a jaxlie group or an Open3D point cloud: `check_not_foreign`). A Python
    number (`0`, `1`) states no dtype and becomes the default float (float64 under x64). Host
    floats are transferred (`to_device`), not converted by a compiled program."""
    check_not_foreign(x, what)
    if isinstance(x, (int, float)) and not isinstance(x, bool):
        x = np.asarray(x, dtype=jnp.result_type(float))
    if isinstance(x, np.ndarray) and np.issubdtype(x.dtype, np.floating):
        x = to_device(x)
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


def states_dtype(x) -> bool:
    """Whether `x` fixes a dtype: JAX arrays and NumPy arrays do; Python numbers and sequences,
    NumPy scalars, 0-d NumPy arrays and weakly typed JAX values (a Python number passed through
    `jit`) do not."""
    if isinstance(x, np.ndarray):
        return x.ndim > 0
    if isinstance(x, jax.Array):  # tracers included
        return not jax.typeof(x).weak_type
    return False


def match_dtype(x, dtype, what: str, owner: str) -> jnp.ndarray:
    """`x` as a float array of `dtype` (the dtype of `owner`, a group or array named in errors): a
    value that states no dtype (`states_dtype`) takes it; an array of another float dtype is a
    `TypeError` naming both dtypes (JAX would promote it, and differentiating the promoted result
    with respect to the narrower input fails inside JAX)."""
    array = as_float_array(x, what)
    if array.dtype == dtype:
        return array
    if not states_dtype(x):
        return array.astype(dtype)
    raise TypeError(
        f"{what} has dtype {array.dtype} but {owner} has dtype {jnp.dtype(dtype)}; "
        f"cast one of them (for example `jnp.asarray(x, {jnp.dtype(dtype)})`)."
    )


def _common_float(what: str, values):
    """`(arrays, dtype)`: `values` as float arrays (each checked once by `as_float_array`) and the
    dtype of those that state one (`states_dtype`; they must agree, else a `TypeError` naming the
    dtypes), the default float when none does."""
    arrays = [as_float_array(v, what) for v in values]
    stated = sorted({str(a.dtype) for a, v in zip(arrays, values) if states_dtype(v)})
    if len(stated) > 1:
        raise TypeError(f"{what}: arguments of different dtypes {' and '.join(stated)}.")
    return arrays, np.dtype(stated[0] if stated else jnp.result_type(float))


def common_float_arrays(what: str, *values) -> list:
    """`values` as float arrays of one dtype: that of the arguments that state a dtype
    (`states_dtype`; they must agree, else a `TypeError` naming the dtypes), the others taking it;
    the default float when none does."""
    arrays, dtype = _common_float(what, values)
    return [a.astype(dtype) for a in arrays]


def common_host_arrays(what: str, *values) -> list:
    """`common_float_arrays` for concrete values, as NumPy arrays (no compilation)."""
    _, dtype = _common_float(what, values)
    return [np.asarray(v).astype(dtype) for v in values]


def check_positive(x, what: str) -> None:
    """A `ValueError` naming `what` if a concrete `x` has an entry that is not positive and finite
    (nonpositive, infinite or NaN); traced values are not checked (see the caller's docstring)."""
    if isinstance(x, jax.core.Tracer):
        return
    values = np.asarray(x)
    bad = ~(np.isfinite(values) & (values > 0))
    if np.any(bad):
        raise ValueError(
            f"{what} must be positive and finite, got {values[bad].ravel()[0]!r}"
            f"{f' (and {int(bad.sum()) - 1} more)' if bad.sum() > 1 else ''}."
        )


def check_same_dtype(what: str, dtype, other_dtype) -> None:
    """A `TypeError` naming `what` and both dtypes unless they are the same."""
    if jnp.dtype(dtype) != jnp.dtype(other_dtype):
        raise TypeError(
            f"{what}: dtypes {jnp.dtype(dtype)} and {jnp.dtype(other_dtype)} differ; cast one of "
            f"them (for example with `type(X)(X.parameters().astype(...))`)."
        )
