r"""Dense normal equations: assembly $H = J^\top W J$, $g = J^\top W r$, and a symmetric
positive-definite solve by Cholesky with a regularized fallback.

The solvers use this for small states (one pose, a handful of variables): `H` is `n × n` with
`n` the tangent dimension of the state, so its factorization costs nothing next to the residual
evaluation over thousands of data points.
"""

import jax
import jax.numpy as jnp
from jax import lax
from jax.scipy.linalg import cho_solve, solve_triangular

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


def damping_for_radius(matrix, rhs, radius, damping, max_tries: int = 10):
    r"""MINPACK's `lmpar`: the Levenberg parameter $\mu \ge 0$ whose step
    $z(\mu) = (A + \mu I)^{-1} b$ has $\|z(\mu)\| \le \Delta$, for a symmetric positive
    semi-definite $A$ (`matrix`), $b$ (`rhs`) and the radius $\Delta$ (`radius`): $\mu = 0$
    when the Gauss-Newton step has $\|z(0)\| \le 1.1\,\Delta$, otherwise $\mu > 0$ with
    $|\,\|z(\mu)\| - \Delta| \le 0.1\,\Delta$, or the last of `max_tries` tries.

    With $\varphi(\mu) = \|z(\mu)\| - \Delta$ and
    $\psi(\mu) = z^\top (A + \mu I)^{-1} z / \|z\|^2 = \|L^{-1} z\|^2 / \|z\|^2$
    ($L L^\top = A + \mu I$), each try takes the Newton step of $1/\|z(\mu)\| - 1/\Delta$
    (Hebden's), $\mu \leftarrow \max(\mu_l,\ \mu + \varphi(\mu) / (\Delta\,\psi(\mu)))$,
    inside a bracket $[\mu_l, \mu_u]$ that starts at $\mu_l = \varphi(0) / (\Delta\,\psi(0))$
    and $\mu_u = \|b\| / \Delta$ and closes on the tries that fall short ($\varphi > 0$:
    $\mu_l \leftarrow \mu$) or overshoot ($\varphi < 0$: $\mu_u \leftarrow \mu$). The first
    try is `damping` (the previous $\mu$, as `lmder` updates it) clipped to the bracket,
    $\|b\| / \|z(0)\|$ if that is 0; a try at 0 is moved to $\max(\text{tiny},
    10^{-3}\mu_u)$ (Moré, "The Levenberg-Marquardt algorithm: implementation and theory",
    1978, Sec. 5; MINPACK's `lmpar`, Garbow, Hillstrom and Moré, 1980).

    MINPACK works on a QR factorization of the Jacobian, and for a rank-deficient one starts
    from $\mu_l = 0$ (and also stops when $\varphi < 0$ stops improving). Here each try factors
    the normal equations with `cholesky_with_fallback`, the factorization the step itself is
    then solved with, so that the radius is measured on the step that will be taken; the
    Gauss-Newton step of a numerically singular $A$ is the regularized one, and $\mu_l$ comes
    from it (should that overshoot the root, the tries end at $\mu_l$, a step shorter than
    $\Delta$). Returns $\mu$; not differentiated (it chooses the path).
    """
    matrix, rhs, radius, damping = lax.stop_gradient((matrix, rhs, radius, damping))
    dtype = matrix.dtype
    tiny = jnp.finfo(dtype).tiny
    identity = jnp.eye(matrix.shape[-1], dtype=dtype)

    def attempt(mu):
        r"""$\|z(\mu)\|$ and $\psi(\mu)$."""
        factor = cholesky_with_fallback(matrix + mu * identity)
        z = solve_factored(factor, rhs)
        norm = jnp.sqrt(jnp.sum(z**2))
        w = solve_triangular(factor, z / jnp.maximum(norm, tiny), lower=True)
        return norm, jnp.sum(w**2)

    norm, psi = attempt(jnp.zeros((), dtype))
    fp = norm - radius
    gauss_newton = fp <= 0.1 * radius
    lower = jnp.where(gauss_newton, 0.0, fp / (radius * psi))
    gradient_norm = jnp.sqrt(jnp.sum(rhs**2))
    upper = gradient_norm / radius
    upper = jnp.where(upper == 0, tiny / jnp.minimum(radius, 0.1), upper)
    mu = jnp.minimum(jnp.maximum(damping, lower), upper)
    mu = jnp.where(mu == 0, gradient_norm / jnp.maximum(norm, tiny), mu)

    def running(carry):
        return ~carry[-1]

    def body(carry):
        tries, mu, lower, upper, _ = carry
        tries = tries + 1
        mu = jnp.where(mu == 0, jnp.maximum(tiny, 1e-3 * upper), mu)
        norm, psi = attempt(mu)
        fp = norm - radius
        done = (jnp.abs(fp) <= 0.1 * radius) | (tries == max_tries)
        lower_new = jnp.where(fp > 0, jnp.maximum(lower, mu), lower)
        upper_new = jnp.where(fp < 0, jnp.minimum(upper, mu), upper)
        mu_new = jnp.maximum(lower_new, mu + fp / (radius * psi))
        return (
            tries,
            jnp.where(done, mu, mu_new),
            jnp.where(done, lower, lower_new),
            jnp.where(done, upper, upper_new),
            done,
        )

    carry = (jnp.zeros((), jnp.int32), mu, lower, upper, gauss_newton)
    mu = lax.while_loop(running, body, carry)[1]
    return jnp.where(gauss_newton, jnp.zeros((), dtype), mu)
