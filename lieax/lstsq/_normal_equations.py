r"""Dense normal equations: assembly $H = J^\top W J$, $g = J^\top W r$, and a symmetric
positive-definite solve by Cholesky with a regularized fallback.

The solvers use this for small states (one pose, a handful of variables): `H` is `n × n` with
`n` the tangent dimension of the state, so its factorization costs nothing next to the residual
evaluation over thousands of data points.
"""

import jax
import jax.numpy as jnp
from jax import lax
from jax.scipy.linalg import cho_solve

# no TF32 on GPUs: the normal equations square the condition number
_HIGHEST = lax.Precision.HIGHEST


def normal_equations(jac, residual, weights=None):
    r"""$H = J^\top W J$ and $g = J^\top W r$ for `jac` `(m, n)`, `residual` `(m,)` and optional
    per-row weights `(m,)` ($W = I$ when `None`)."""
    weighted = jac if weights is None else jac * weights[:, None]
    hessian = jnp.matmul(weighted.T, jac, precision=_HIGHEST)
    gradient = jnp.matmul(weighted.T, residual, precision=_HIGHEST)
    return hessian, gradient


def cholesky_with_fallback(matrix):
    r"""A lower Cholesky factor $L$ ($L L^\top = A$) of `matrix`, or of `matrix`
    $+ \epsilon\,\mathrm{diag}(A)$ when the plain factorization fails or is numerically
    singular.

    The factorization is of the Jacobi-scaled $\tilde A = S^{-1} A S^{-1}$,
    $S = \mathrm{diag}(\sqrt{A_{jj}})$ (1 for a zero diagonal), and $L = S \tilde L$: the
    tests below do not depend on the units of the unknowns, so a well-posed problem whose
    variables differ in size by many orders of magnitude is not taken for a singular one.
    Singular means a pivot
    $\tilde\ell_{jj}^2 \le 10\,n\,\varepsilon \max_i \tilde A_{ii}$ (a state with a gauge
    freedom, a variable no residual touches). The fallback adds
    $\epsilon = \sqrt{\varepsilon} \max_i \tilde A_{ii}$ to the diagonal of $\tilde A$: for a
    positive semi-definite $A = J^\top W J$ and a right side in its range ($J^\top W r$), the
    solution then has no component along the null space of $\tilde A$ (it is the one of least
    $\|S x\|$) and is shortened by $\lambda / (\lambda + \epsilon)$ along each eigenvector of
    $\tilde A$ elsewhere. An indefinite or non-finite matrix gives NaN.

    Both factorizations are computed and one is selected (no `lax.cond`): for the small
    matrices this is for, a second factorization costs less than a branch in the compiled loop,
    and under `vmap` a branch would compute both anyway.
    """
    n = matrix.shape[-1]
    if n == 0:
        return matrix
    eps = jnp.finfo(matrix.dtype).eps
    diagonal = jnp.diagonal(matrix)
    scale = jnp.sqrt(jnp.where(diagonal > 0, diagonal, 1.0))
    scaled = matrix / (scale[:, None] * scale[None, :])
    largest = jnp.max(jnp.abs(jnp.diagonal(scaled)))
    factor = jnp.linalg.cholesky(scaled)
    pivots = jnp.diagonal(factor)
    ok = jnp.all(jnp.isfinite(factor)) & (jnp.min(pivots) ** 2 > 10 * n * eps * largest)
    shift = jnp.sqrt(eps) * jnp.maximum(largest, jnp.finfo(matrix.dtype).tiny)
    regularized = jnp.linalg.cholesky(scaled + shift * jnp.eye(n, dtype=matrix.dtype))
    return scale[:, None] * jnp.where(ok, factor, regularized)


def solve_factored(factor, rhs):
    """$A^{-1} b$ from the lower Cholesky factor of $A$; linear in `rhs` (so it transposes)."""
    if factor.shape[-1] == 0:
        return rhs
    return cho_solve((factor, True), rhs)


@jax.custom_jvp
def solve_spd(matrix, rhs):
    r"""$A^{-1} b$ for a symmetric positive (semi-)definite $A$, through `cholesky_with_fallback`.

    Its derivative is $\dot x = A^{-1}(\dot b - \dot A x)$ with the same factor (the fallback's
    shift is held constant), so differentiating an unrolled solve never goes through a failed
    factorization.
    """
    return solve_factored(cholesky_with_fallback(matrix), rhs)


@solve_spd.defjvp
def _solve_spd_jvp(primals, tangents):
    (matrix, rhs), (matrix_dot, rhs_dot) = primals, tangents
    factor = cholesky_with_fallback(matrix)
    solution = solve_factored(factor, rhs)
    return solution, solve_factored(factor, rhs_dot - matrix_dot @ solution)
