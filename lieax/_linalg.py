"""Vector and quaternion algebra on the last axis: cross and dot products, matrix-vector
products as contractions, skew matrices, Hamilton products of wxyz quaternions; and the
polynomials of the closed forms' series (`horner`).

Plain JAX functions (no custom rules: JAX differentiates these polynomials exactly), shared by the
groups, the conventions converters, ICP and bundle adjustment. Components are taken with
`components` (`jax.lax` slices, what `x[..., i]` stages, without its indexing machinery: these
functions are in every group operation and its rules, and are traced again by every
transformation).
"""

import jax.numpy as jnp
import numpy as np
from jax import lax


def components(x, count):
    """`[x[..., 0], ..., x[..., count - 1]]`, the first `count` entries of the last axis."""
    return [lax.index_in_dim(x, i, axis=-1, keepdims=False) for i in range(count)]


def cross(a, b):
    a0, a1, a2 = components(a, 3)
    b0, b1, b2 = components(b, 3)
    return jnp.stack([a1 * b2 - a2 * b1, a2 * b0 - a0 * b2, a0 * b1 - a1 * b0], axis=-1)


def dot(a, b):
    return jnp.sum(a * b, axis=-1)


def matvec(matrix, x):
    """$M x$ as a contraction (`dot_general`), not a broadcast product and sum: XLA's CPU backend
    runs the contraction and its transpose several times faster (see benchmarks/chain.py)."""
    return jnp.einsum("...ij,...j->...i", matrix, x)


def skew(v):
    r"""$[v]_\times$, with $[v]_\times x = v \times x$."""
    v0, v1, v2 = components(v, 3)
    zero = jnp.zeros_like(v0)
    rows = [[zero, -v2, v1], [v2, zero, -v0], [-v1, v0, zero]]
    return jnp.stack([jnp.stack(row, axis=-1) for row in rows], axis=-2)


def unskew(m):
    r"""The vector of the skew part of `m`: $\mathrm{vee}((m - m^\top)/2)$."""
    return 0.5 * jnp.stack(
        [m[..., 2, 1] - m[..., 1, 2], m[..., 0, 2] - m[..., 2, 0], m[..., 1, 0] - m[..., 0, 1]],
        axis=-1,
    )


def quat_multiply(a, b):
    r"""Hamilton product $a \otimes b$ of wxyz quaternions."""
    aw, ax, ay, az = components(a, 4)
    bw, bx, by, bz = components(b, 4)
    return jnp.stack(
        [
            aw * bw - ax * bx - ay * by - az * bz,
            aw * bx + ax * bw + ay * bz - az * by,
            aw * by - ax * bz + ay * bw + az * bx,
            aw * bz + ax * by - ay * bx + az * bw,
        ],
        axis=-1,
    )


def quat_conjugate(q):
    return q * jnp.array([1.0, -1.0, -1.0, -1.0], dtype=q.dtype)


def quat_rotate(q, p):
    r"""$R(q)\,p = p + w\,t + u \times t$ with $t = 2\,u \times p$ (unit $q = (w, u)$)."""
    w, u = q[..., :1], q[..., 1:]
    t = 2.0 * cross(u, p)
    return p + w * t + cross(u, t)


def quat_to_matrix(q):
    r"""$R(q) = (w^2 - u^\top u) I + 2 u u^\top + 2 w [u]_\times$, written out."""
    w, x, y, z = components(q, 4)
    xx, yy, zz = x * x, y * y, z * z
    xy, xz, yz, wx, wy, wz = x * y, x * z, y * z, w * x, w * y, w * z
    rows = [
        [1 - 2 * (yy + zz), 2 * (xy - wz), 2 * (xz + wy)],
        [2 * (xy + wz), 1 - 2 * (xx + zz), 2 * (yz - wx)],
        [2 * (xz - wy), 2 * (yz + wx), 1 - 2 * (xx + yy)],
    ]
    return jnp.stack([jnp.stack(row, axis=-1) for row in rows], axis=-2)


def rotate_back(rotation, x):
    r"""$R^\top x$."""
    return jnp.einsum("...ji,...j->...i", rotation, x)


def blocks(rows):
    """A block matrix from a nested list of `(*batch, n_i, m_j)` blocks (rows of equal height)."""
    return jnp.concatenate([jnp.concatenate(row, axis=-1) for row in rows], axis=-2)


def horner(coefficients, s, xp=jnp):
    r"""$\sum_k c_k s^k$ of `coefficients` $(c_0, c_1, \dots)$ by Horner's rule, in the array
    namespace `xp`. With `jax.numpy`, in `jax.lax` primitives: each `jnp` operator is a small
    jitted function that every transformation traces again (an 11-term series stages 20 of
    them), and the series are in every closed form; the same operations in the same order, so
    the same values."""
    if xp is not jnp:
        result = xp.full_like(s, coefficients[-1])
        for c in reversed(coefficients[:-1]):
            result = result * s + c
        return result
    s = jnp.asarray(s)
    result = lax.full_like(s, coefficients[-1])
    for c in reversed(coefficients[:-1]):
        result = lax.add(lax.mul(result, s), np.asarray(c, s.dtype))
    return result
