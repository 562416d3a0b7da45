r"""Batched Cholesky factors, their inverses and solves on the host (NumPy and LAPACK), for the
NumPy path of the multifrontal Cholesky (`_multifrontal.CholeskyPlan.factor`, `solve_factored`),
written so that they wake one OpenBLAS thread pool only (see the note below).
"""

import numpy as np

# Host linear algebra must not wake two OpenBLAS thread pools: SciPy's wheels bundle a second
# OpenBLAS beside NumPy's, and two pools busy-waiting in one process are the slowest configuration
# on a small machine (sphere2500 took 7.8x as long with both pools at two threads as with either
# at one, 2 cores). So every operation that OpenBLAS may run on several threads (products of
# 64³ multiply-adds and more, factorizations of order 64 and more) is NumPy's, and SciPy's LAPACK
# is called only on triangles of order below 64, which OpenBLAS always inverts on the calling
# thread (`trtri` falls back to its unblocked `trti2` there; measured: process CPU time equals
# wall time up to order 64, twice it from 96 with two threads allowed). NumPy has no triangular
# inverse, and `numpy.linalg.inv` (LU) is 2.5-3.5x slower than `trtri` from order 12 up, so
# larger triangles are a blocked recursion on NumPy products (Higham, "Accuracy and Stability of
# Numerical Algorithms", Sec. 14.2) down to blocks below 64, and the tiniest (order ≤ 8, where
# the per-call cost dominates) are one batched `numpy.linalg.inv`.
_SINGLE_THREAD_LIMIT = 64
_BATCHED_LIMIT = 8


def _lower_inverse(lower):
    r"""$L^{-1}$ for a batch `(B, n, n)` of lower-triangular $L$:
    $[A, 0; C, D]^{-1} = [A^{-1}, 0; -D^{-1} C A^{-1}, D^{-1}]$ for $n \ge 64$, LAPACK's
    `trtri` one matrix at a time below, one batched `numpy.linalg.inv` up to order 8."""
    n = lower.shape[-1]
    if n <= _BATCHED_LIMIT:
        return np.linalg.inv(lower)
    if n < _SINGLE_THREAD_LIMIT:
        return _trtri_each(lower)
    h = n // 2
    a_inv = _lower_inverse(lower[:, :h, :h])
    d_inv = _lower_inverse(lower[:, h:, h:])
    result = np.zeros_like(lower)
    result[:, :h, :h] = a_inv
    result[:, h:, h:] = d_inv
    result[:, h:, :h] = -(d_inv @ (lower[:, h:, :h] @ a_inv))
    return result


def _cholesky_inverse(matrix):
    r"""$L^{-1}$ for the Cholesky factors $L L^\top$ of a batch `(B, n, n)` of symmetric positive
    definite matrices (only their lower triangles are read): for orders 9 to 63, LAPACK's `potrf`
    and `trtri` one matrix at a time on the same Fortran-ordered copy (below order 64 OpenBLAS
    runs both on the calling thread, see `_SINGLE_THREAD_LIMIT`), which skips the batched
    `numpy.linalg.cholesky`'s layout copies and calls; `_lower_inverse` of
    `numpy.linalg.cholesky` otherwise."""
    n = matrix.shape[-1]
    if n <= _BATCHED_LIMIT or n >= _SINGLE_THREAD_LIMIT:
        return _lower_inverse(np.linalg.cholesky(matrix))
    from scipy.linalg import lapack

    potrf, trtri = lapack.get_lapack_funcs(("potrf", "trtri"), (matrix,))
    result = np.empty_like(matrix)
    for b in range(matrix.shape[0]):
        # the C-ordered lower triangle is the Fortran-ordered upper triangle of the transpose
        upper, info = potrf(matrix[b].T, lower=0, clean=1)
        if info != 0:
            raise np.linalg.LinAlgError("matrix is not positive definite")
        inverse, info = trtri(upper, lower=0, overwrite_c=1)
        if info != 0:
            raise np.linalg.LinAlgError("singular triangular factor")
        result[b] = inverse.T
    return result


def _cholesky_solve(lower, rhs):
    r"""$(L L^\top)^{-1}$ `rhs` for a batch `(B, n, n)` of lower-triangular $L$ and `rhs`
    `(B, n, 1)`: LAPACK's `potrs` one matrix at a time (in place on the transpose, as
    `_trtri_each`). With one right-hand side OpenBLAS's triangular solves stay on the calling
    thread at every order (measured with two threads allowed: process CPU time equals wall time
    up to order 400), and one call does both substitutions of a root front: 12 µs where two
    blocked triangular solves (recursions on NumPy products, as `_lower_inverse`'s) took 50 µs
    (order 180, smallGrid3D's root)."""
    from scipy.linalg import lapack

    (potrs,) = lapack.get_lapack_funcs(("potrs",), (lower,))
    result = np.empty_like(rhs)
    for b in range(lower.shape[0]):
        result[b], info = potrs(lower[b].T, rhs[b], lower=0)
        if info != 0:
            raise np.linalg.LinAlgError("singular triangular factor")
    return result


def _trtri_each(lower):
    """`trtri` on each matrix of the batch. A C-ordered lower triangle is the Fortran-ordered
    upper triangle of its transpose, so LAPACK reads it in place and the transpose of its result
    is the inverse."""
    from scipy.linalg import lapack

    (trtri,) = lapack.get_lapack_funcs(("trtri",), (lower,))
    result = np.empty_like(lower)
    for b in range(lower.shape[0]):
        inverse, info = trtri(lower[b].T, lower=0)
        if info != 0:
            raise np.linalg.LinAlgError("singular triangular factor")
        result[b] = inverse.T
    return result
