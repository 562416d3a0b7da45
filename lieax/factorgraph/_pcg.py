r"""Conjugate gradients on the block normal equations (`_block_pattern`), preconditioned by the
inverse diagonal blocks (block Jacobi), with matrix-vector products by segment sums: no
factorization, for large graphs on GPUs (Saad, "Iterative Methods for Sparse Linear Systems",
2003, Alg. 9.1).
"""

import jax
import jax.numpy as jnp
from jax import lax

from ._block_pattern import block_matvec


def pcg(pattern, diag, off, rhs, *, tolerance=1e-10, max_iterations=None):
    r"""Solve $H x = b$ by conjugate gradients preconditioned with the inverse diagonal blocks.

    Stops when $\|r\| \le$ `tolerance` $\|b\|$ or after `max_iterations` (default $10 n d$).
    **Returns:** `(x, iterations)`.
    """
    n, d = pattern.num_blocks, pattern.block_size
    max_iterations = 10 * n * d if max_iterations is None else max_iterations
    chol = jnp.linalg.cholesky(diag)

    def precondition(r):
        return jax.scipy.linalg.cho_solve((chol, True), r[..., None])[..., 0]

    def matvec(x):
        return block_matvec(pattern, diag, off, x)

    x = jnp.zeros_like(rhs)
    r = rhs
    z = precondition(r)
    rz = jnp.vdot(r, z)
    threshold = (tolerance * jnp.linalg.norm(rhs)) ** 2

    def cond(state):
        _, r, _, _, _, k = state
        return (jnp.vdot(r, r) > threshold) & (k < max_iterations)

    def body(state):
        x, r, z, p, rz, k = state
        q = matvec(p)
        alpha = rz / jnp.vdot(p, q)
        x = x + alpha * p
        r = r - alpha * q
        z = precondition(r)
        rz_new = jnp.vdot(r, z)
        p = z + (rz_new / rz) * p
        return x, r, z, p, rz_new, k + 1

    x, _, _, _, _, k = lax.while_loop(cond, body, (x, r, z, z, rz, jnp.zeros((), jnp.int32)))
    return x, k


__all__ = ["pcg"]
