r"""Manifold-local Jacobians and gradients of functions of pytrees that mix groups and arrays.

The Jacobian of $f: \mathcal{M} \to \mathcal{N}$ at $X$ is the matrix $J$ with
$f(X \oplus \delta) \ominus f(X) \approx J\,\delta$, in right-local tangent coordinates on both
sides (for arrays $\oplus$ is $+$). It is computed by one linearization of `f` in the parameters,
seeded with the JAX tangent that moves $X$ along $\delta$ (each group's `_tangent_from_local`; for
SO3 and SE3 the local tangent itself) and read out with the inverse map at $f(X)$. Because every group kernel carries a closed-form `custom_jvp`
rule, the linearization costs what the hand-written block Jacobians cost: nothing is ever
differentiated through Exp, Log or the quaternion embedding.

Forward mode pushes one tangent direction per input coordinate; reverse mode pulls one cotangent
per output coordinate. `mode="auto"` takes the smaller count.
"""

import math
from collections.abc import Callable, Sequence

import jax
import jax.numpy as jnp

from ..groups import AbstractManifold, kernels
from ._tangents import (
    leaf_array,
    leaf_local_from_tangent,
    leaf_tangent_from_local,
    leaf_tangent_shape,
    manifold_leaves,
)

_MODES = ("auto", "fwd", "rev")


def value_and_jacobian(
    f: Callable, argnums: int | Sequence[int] = 0, *, has_aux: bool = False, mode: str = "auto"
) -> Callable:
    """Like `jacobian`, but the returned function gives `(value, J)`, or `((value, aux), J)` with
    `has_aux`."""
    if mode not in _MODES:
        raise ValueError(f"mode must be one of {_MODES}, got {mode!r}.")
    single = isinstance(argnums, int)
    argnums_tuple = (argnums,) if single else tuple(argnums)

    def evaluate(*args):
        for i in argnums_tuple:
            if not -len(args) <= i < len(args):
                raise ValueError(f"argnums {argnums} out of range for {len(args)} arguments.")
        flattened = [manifold_leaves(args[i], f"argument {i}") for i in argnums_tuple]
        in_leaves = [leaf for leaves, _ in flattened for leaf in leaves]

        def on_leaves(*arrays):
            rebuilt = iter(_rebuild(leaf, a) for leaf, a in zip(in_leaves, arrays))
            full_args = list(args)
            for i, (leaves, treedef) in zip(argnums_tuple, flattened):
                full_args[i] = treedef.unflatten([next(rebuilt) for _ in leaves])
            result = f(*full_args)
            value, aux = result if has_aux else (result, None)
            out_leaves, _ = manifold_leaves(value, "result")
            return [leaf_array(leaf) for leaf in out_leaves], (value, aux)

        primals = [leaf_array(leaf) for leaf in in_leaves]
        _, linear, (value, aux) = jax.linearize(on_leaves, *primals, has_aux=True)
        out_leaves, out_treedef = manifold_leaves(value, "result")

        in_shapes = [leaf_tangent_shape(leaf) for leaf in in_leaves]
        out_shapes = [leaf_tangent_shape(leaf) for leaf in out_leaves]
        in_size = sum(math.prod(s) for s in in_shapes)
        out_size = sum(math.prod(s) for s in out_shapes)
        # seeds and read-outs in each leaf's own dtype (a float32 input may give a float64
        # output), the Jacobian in the widest
        dtype = jnp.result_type(*primals, *(leaf_array(leaf) for leaf in out_leaves))

        use_reverse = mode == "rev" or (mode == "auto" and out_size < in_size)
        if use_reverse:
            transposed = jax.linear_transpose(linear, *primals)

            def pull(cotangent):
                pieces = _split(cotangent, out_shapes)
                seeds = [
                    _transpose_local_from_tangent(y, c.astype(leaf_array(y).dtype))
                    for y, c in zip(out_leaves, pieces)
                ]
                pulled = transposed(seeds)
                return jnp.concatenate(
                    [
                        jnp.ravel(_transpose_tangent_from_local(x, a)).astype(dtype)
                        for x, a in zip(in_leaves, pulled)
                    ]
                )

            flat = jax.vmap(pull)(jnp.eye(out_size, dtype=dtype))
            rows = [flat[a:b] for a, b in _offsets(out_shapes)]
        else:

            def push(direction):
                pieces = _split(direction, in_shapes)
                seeds = [
                    leaf_tangent_from_local(x, d.astype(leaf_array(x).dtype))
                    for x, d in zip(in_leaves, pieces)
                ]
                pushed = linear(*seeds)
                # one array per output leaf, never concatenated: a leaf sharded along its rows
                # (lieax.sharding.shard_residuals) keeps its sharding, and none is copied
                return [
                    jnp.ravel(leaf_local_from_tangent(y, t)) for y, t in zip(out_leaves, pushed)
                ]

            rows = jax.vmap(push, out_axes=1)(jnp.eye(in_size, dtype=dtype))

        jac = out_treedef.unflatten(
            [
                _input_structure(leaf_rows, out_shape, in_shapes, flattened, single)
                for leaf_rows, out_shape in zip(rows, out_shapes)
            ]
        )
        return ((value, aux) if has_aux else value), jac

    return evaluate


def jacobian(
    f: Callable, argnums: int | Sequence[int] = 0, *, has_aux: bool = False, mode: str = "auto"
) -> Callable:
    r"""The manifold-local Jacobian of `f`: $f(X \oplus \delta) \ominus f(X) \approx J\,\delta$.

    **Arguments:**

    - `f`: a function whose arguments and result are groups, arrays or pytrees of them.
    - `argnums`: which arguments to differentiate (an int or a tuple of ints).
    - `has_aux`: `f` returns `(value, aux)`; the Jacobian function then returns `(J, aux)`.
    - `mode`: `"fwd"`, `"rev"`, or `"auto"` (reverse when the output tangent is smaller).

    **Returns:** a function of `f`'s arguments returning `J`, nested like `jax.jacobian`'s (result
    structure outside, argument structure inside; a tuple over `argnums` when it is a tuple), each
    block of shape `(*out_tangent_shape, *in_tangent_shape)`; a group's tangent shape is
    `(*batch, tangent_dim)`, an array's is its shape.
    """
    with_value = value_and_jacobian(f, argnums, has_aux=has_aux, mode=mode)

    def evaluate(*args):
        value, jac = with_value(*args)
        return (jac, value[1]) if has_aux else jac

    return evaluate


def value_and_grad(
    f: Callable, argnums: int | Sequence[int] = 0, *, has_aux: bool = False
) -> Callable:
    """`(value, grad)` of a scalar function (`((value, aux), grad)` with `has_aux`)."""

    def scalar_f(*args):
        result = f(*args)
        value = result[0] if has_aux else result
        if isinstance(value, AbstractManifold) or jnp.shape(value) != ():
            raise TypeError(
                f"grad needs a function with a scalar result, got {_describe(value)}; "
                "use lieax.jacobian for other results."
            )
        return result

    return value_and_jacobian(scalar_f, argnums, has_aux=has_aux, mode="rev")


def grad(f: Callable, argnums: int | Sequence[int] = 0, *, has_aux: bool = False) -> Callable:
    r"""The gradient of a scalar function in tangent coordinates: group leaves get tangent vectors
    $\nabla_\delta f(X \oplus \delta)|_{\delta=0}$, shape `(*batch, tangent_dim)`."""
    with_value = value_and_grad(f, argnums, has_aux=has_aux)

    def evaluate(*args):
        value, gradient = with_value(*args)
        return (gradient, value[1]) if has_aux else gradient

    return evaluate


# ---- helpers -------------------------------------------------------------------------------------


def _rebuild(leaf, array):
    return kernels.element(type(leaf), array) if isinstance(leaf, AbstractManifold) else array


def _transpose_local_from_tangent(leaf, local_cotangent):
    """Transpose of the read-out map at an output leaf: local cotangent to leaf cotangent."""
    zeros = jnp.zeros_like(leaf_array(leaf))
    (cotangent,) = jax.linear_transpose(lambda t: leaf_local_from_tangent(leaf, t), zeros)(
        local_cotangent
    )
    return cotangent


def _transpose_tangent_from_local(leaf, cotangent):
    """Transpose of the seeding map at an input leaf: leaf cotangent to local cotangent."""
    zeros = jnp.zeros(leaf_tangent_shape(leaf), dtype=cotangent.dtype)
    (local,) = jax.linear_transpose(lambda d: leaf_tangent_from_local(leaf, d), zeros)(cotangent)
    return local


def _offsets(shapes):
    """`(start, stop)` of each shape's entries in a flat vector."""
    bounds, start = [], 0
    for shape in shapes:
        bounds.append((start, start + math.prod(shape)))
        start += math.prod(shape)
    return bounds


def _split(vector, shapes):
    return [jnp.reshape(vector[a:b], shape) for (a, b), shape in zip(_offsets(shapes), shapes)]


def _input_structure(rows, out_shape, in_shapes, flattened, single):
    """One output leaf's block row, split into blocks and nested like the differentiated args."""
    blocks = iter(
        jnp.reshape(rows[:, a:b], (*out_shape, *in_shape))
        for (a, b), in_shape in zip(_offsets(in_shapes), in_shapes)
    )
    per_argument = [
        treedef.unflatten([next(blocks) for _ in leaves]) for leaves, treedef in flattened
    ]
    return per_argument[0] if single else tuple(per_argument)


def _describe(value):
    if isinstance(value, AbstractManifold):
        return f"a {type(value).__name__}"
    return f"shape {jnp.shape(value)}"
