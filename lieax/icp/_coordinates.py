"""Sums and the rigid motion of points written out for XLA's CPU backend: over the three
coordinates of points, and of several arrays over their rows at once.

XLA's CPU backend (jaxlib 0.10.2) compiles `jnp.sum(x, axis=-1)` of an `(n, 3)` array as a
YNNPACK reduction kernel of its own, 3-4x slower than the two additions of the columns, which
fuse with the gathers and products around them into one loop (10k float64 rows: 145 µs against
53 µs; a gathered squared distance 219 µs against 55 µs). ICP computes such sums every iteration.
"""

import jax
import jax.numpy as jnp

from .._linalg import quat_to_matrix


def coordinate_sum(x):
    """`x[..., 0] + x[..., 1] + x[..., 2]`, for `x` of shape `(..., 3)`."""
    return x[..., 0] + x[..., 1] + x[..., 2]


def squared_norms(x):
    r"""$\|x\|^2$ of each row of `x` `(..., 3)`, shape `(...)`."""
    return coordinate_sum(x * x)


def row_sums(terms):
    """The sums of the `(n,)` arrays `terms`, as one variadic reduction: XLA's CPU backend
    computes it in one fused loop, where `jnp.sum` of each term (or a matrix product) first
    writes the terms out."""
    zeros = tuple(jnp.zeros((), term.dtype) for term in terms)
    add = lambda a, b: tuple(x + y for x, y in zip(a, b))
    return list(jax.lax.reduce(tuple(terms), zeros, add, (0,)))


def transform_points(params, points):
    """$R p + t$ for SE3 parameters `(w, x, y, z, tx, ty, tz)` and points `(n, 3)`, written out per
    coordinate: `SE3.act`'s values (its contraction agrees with float64 in float32 at 20k points,
    `tests/test_icp_invariance.py`), 1.5-7x faster on 20k points on the CPU and 7-10x under
    `vmap` (jaxlib 0.10.2, float64 and float32)."""
    return jnp.stack(transformed_columns(params, points), axis=1)


def transformed_columns(params, points):
    """The three coordinates of `transform_points(params, points)`, each `(n,)` (a step that
    reduces over them needs no `(n, 3)` array)."""
    rotation = quat_to_matrix(params[:4])
    x, y, z = points[:, 0], points[:, 1], points[:, 2]
    return [
        rotation[i, 0] * x + rotation[i, 1] * y + rotation[i, 2] * z + params[4 + i]
        for i in range(3)
    ]
