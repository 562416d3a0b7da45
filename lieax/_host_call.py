"""`host_call`: a NumPy function called on the host from traced code (`jit`, `vmap`, loops).

The solvers call host code once per iteration (the multifrontal Cholesky of `lieax.graph`, the
host k-d trees of `lieax.icp`). `jax.pure_callback` puts every operand on a device as a
`jax.Array` and converts the result back, about 0.2 ms per call for a pose graph's normal equations
(10% of an iteration on smallGrid3D); the primitive here hands XLA's host buffers to the function
as NumPy arrays (7 µs). It lowers through JAX's `emit_python_callback`, which is not public API:
`_primitive_supported` checks what the lowering relies on (the function exists and takes
`has_side_effect` and `returns_token`), and where it does not hold, `host_call` is
`pure_callback_host_call`, the public-API path. Both give the same results (tests/test_host_call.py
runs each); this is the only module that imports JAX internals.
"""

import inspect

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax


def pure_callback_host_call(fn, result, *args, batched=None):
    """`host_call` through `jax.pure_callback` (public API; slower per call)."""
    if batched is None:
        return jax.pure_callback(
            lambda *a: np.asarray(fn(*(np.asarray(x) for x in a)), result.dtype),
            result,
            *args,
            vmap_method="sequential",
        )
    ranks = [jnp.ndim(a) for a in args]

    def call(*arrays):  # under (nested) vmap every operand carries the same leading batch axes
        arrays = [np.asarray(x) for x in arrays]
        lead = arrays[0].ndim - ranks[0]
        if not lead:
            return np.asarray(fn(*arrays), result.dtype)
        return np.asarray(_on_flattened(batched, arrays, lead, result.shape), result.dtype)

    return jax.pure_callback(call, result, *args, vmap_method="broadcast_all")


def host_call(fn, result, *args, batched=None):
    """`fn(*args)` on the host, from traced code.

    **Arguments:**

    - `fn`: takes NumPy arrays and returns one NumPy array (a pure function of its inputs).
    - `result`: a `jax.ShapeDtypeStruct`, the shape and dtype of `fn`'s result.
    - `args`: JAX arrays.
    - `batched`: optional, `fn` over a batch: takes every argument with one leading batch axis
      `(B, ...)` and returns `(B, *result.shape)`. Under `vmap` (nested or not) it is called once
      for the whole batch; without it, `fn` is called once per batch element.

    **Returns:** `fn(*args)` as a JAX array.
    """
    if _HOST_CALL is None:
        return pure_callback_host_call(fn, result, *args, batched=batched)
    return _HOST_CALL.bind(
        *args, fn=fn, shape=tuple(result.shape), dtype=np.dtype(result.dtype), batched=batched
    )


def _on_flattened(batched, arrays, lead, shape):
    """`batched` of `arrays` whose first `lead` axes (the same in each) are batch axes, flattened
    into one; the result reshaped back to `(*those axes, *shape)`."""
    axes = arrays[0].shape[:lead]
    flat = [a.reshape(-1, *a.shape[lead:]) for a in arrays]
    return np.asarray(batched(*flat)).reshape(*axes, *shape)


def _flattening(batched, shape):
    """`batched` for arguments with two leading batch axes `(B1, B0, ...)` (the batching rule of a
    call that is already batched): `_on_flattened` over both."""
    return lambda *arrays: _on_flattened(batched, arrays, 2, shape)


def _primitive_supported(emit_python_callback) -> bool:
    """Whether JAX's internal `emit_python_callback` takes the keywords the lowering passes."""
    parameters = inspect.signature(emit_python_callback).parameters
    return {"has_side_effect", "returns_token"} <= parameters.keys()


def _host_call_primitive():
    """The `lieax_host_call` primitive (implementation, abstract evaluation, lowering, batching),
    or `None` where this JAX lacks what it relies on."""
    try:
        from jax._src.callback import emit_python_callback
        from jax.extend.core import Primitive
        from jax.interpreters import batching, mlir
    except ImportError:  # pragma: no cover - depends on JAX's internals
        return None
    if not _primitive_supported(emit_python_callback):  # pragma: no cover
        return None

    primitive = Primitive("lieax_host_call")

    def impl(*args, fn, shape, dtype, batched):
        return jnp.asarray(np.asarray(fn(*(np.asarray(a) for a in args)), dtype))

    def abstract_eval(*args, fn, shape, dtype, batched):
        return jax.core.ShapedArray(shape, dtype)

    def lowering(ctx, *args, fn, shape, dtype, batched):
        def call(*arrays):
            return (np.asarray(fn(*arrays), dtype),)

        result, _, _ = emit_python_callback(
            ctx,
            call,
            None,
            list(args),
            ctx.avals_in,
            ctx.avals_out,
            has_side_effect=False,
            returns_token=False,
        )
        return result

    def batch(args, dims, *, fn, shape, dtype, batched):
        size = next(a.shape[d] for a, d in zip(args, dims) if d is not None)
        args = [
            jnp.broadcast_to(a, (size, *a.shape)) if d is None else jnp.moveaxis(a, d, 0)
            for a, d in zip(args, dims)
        ]
        if batched is not None:  # one call for the batch
            out = primitive.bind(
                *args, fn=batched, shape=(size, *shape), dtype=dtype,
                batched=_flattening(batched, shape),
            )  # fmt: skip
            return out, 0
        out = lax.map(
            lambda xs: primitive.bind(*xs, fn=fn, shape=shape, dtype=dtype, batched=None), args
        )
        return out, 0

    primitive.def_impl(impl)
    primitive.def_abstract_eval(abstract_eval)
    mlir.register_lowering(primitive, lowering, cacheable=False)
    batching.primitive_batchers[primitive] = batch
    return primitive


_HOST_CALL = _host_call_primitive()
