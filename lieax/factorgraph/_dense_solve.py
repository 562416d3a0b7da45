r"""The dense solver of the block normal equations (`_block_pattern`): the dense matrix and its
Cholesky factor inside JAX, for nearly dense systems of a few hundred unknowns, and for graphs of
up to 300 unknowns where the multifrontal Cholesky has no native library (`linear_solver="auto"`
picks it there: `lieax.factorgraph._graph._auto_method`), and the BLAS threads for it.
"""

import jax
import jax.numpy as jnp
import numpy as np

from .. import _threads
from ._block_pattern import dense_matrix


def dense_solve(pattern, diag, off, rhs):
    """$H^{-1}$ `rhs` through the dense matrix and its Cholesky factor, in JAX; NaN
    when $H$ is not positive definite. The matrix is one gather from the blocks (indices built
    in numpy at trace time), or, for a bucketed graph whose pattern's pairs are operands
    (`_buckets`), sums of the blocks into place (`dense_matrix`)."""
    n, d = pattern.num_blocks, pattern.block_size
    if isinstance(pattern.rows, np.ndarray):
        matrix = gathered_matrix(pattern, diag, off)
    else:
        matrix = dense_matrix(pattern, diag, off)

    def solve(system):
        matrix, b = system
        factor = jnp.linalg.cholesky(matrix)
        return jax.scipy.linalg.cho_solve((factor, True), b)

    return solve((matrix, rhs.reshape(n * d))).reshape(n, d)


def gathered_matrix(pattern, diag, off, xp=jnp):
    """The dense `(n d, n d)` matrix of a host `pattern`'s blocks, one gather from
    `[diag, off, 0]` (`_dense_index`), in the array namespace `xp` (`jax.numpy` inside the solve,
    `numpy` for `marginal_covariances`, which compile nothing)."""
    values = xp.concatenate([diag.reshape(-1), off.reshape(-1), xp.zeros(1, diag.dtype)])
    return values[_dense_index(pattern)]


def dense_threads(pattern):
    """The BLAS threads for `dense_solve`'s factorization of `pattern` on a CPU, to be set around
    the compiled call (`lieax._threads.lapack_limited`), or `None` (no scope): XLA's CPU backend
    factors through SciPy's OpenBLAS, whose idle threads busy-wait, so one thread below
    `lieax._threads.PARALLEL_FLOPS` (order 441, Ladybug-49's cameras: 4 ms against 442 ms on two
    threads on a busy 2-core machine); below order `SINGLE_THREAD_ORDER` OpenBLAS stays on the
    calling thread anyway."""
    order = pattern.num_blocks * pattern.block_size
    if order < _threads.SINGLE_THREAD_ORDER or jax.default_backend() != "cpu":
        return None
    return _threads.threads_for(order**3 / 3, _threads.PARALLEL_FLOPS)


def _dense_index(pattern):
    """For each entry of the dense `(n d, n d)` matrix, its index in `[diag, off, 0]` (flat)."""
    n, d, p = pattern.num_blocks, pattern.block_size, pattern.num_pairs
    index = np.full((n * d, n * d), n * d * d + p * d * d, dtype=np.int32)
    r = np.arange(d)
    a = np.arange(n)[:, None, None]
    index[a * d + r[:, None], a * d + r[None, :]] = (a * d + r[:, None]) * d + r[None, :]
    k = np.arange(p)[:, None, None]
    rows, cols = pattern.rows[:, None, None], pattern.cols[:, None, None]
    source = n * d * d + (k * d + r[:, None]) * d + r[None, :]
    index[rows * d + r[:, None], cols * d + r[None, :]] = source
    index[cols * d + r[None, :], rows * d + r[:, None]] = source
    return index


__all__ = ["dense_solve", "dense_threads", "gathered_matrix"]
