r"""Derivatives of a converged solution by the implicit function theorem, in tangent coordinates.

At a minimum $x^*(\theta)$ of $f(x, \theta) = \tfrac12 \sum_i \rho(\|r_i(x, \theta)\|^2)$
the tangent-space gradient $g(\delta, \theta) = \nabla_\delta f(x^* \oplus \delta, \theta)$
vanishes at $\delta = 0$. Differentiating $g(\delta(\theta), \theta) = 0$ (Ceres' notes, "Using
Inverse & Implicit Function Theorems", on the solution of an optimization problem) gives

$$\dot\delta = -H^{-1}\,\frac{\partial g}{\partial \theta}\,\dot\theta, \qquad
H = \frac{\partial g}{\partial \delta}
  = \nabla^2_\delta f(x^* \oplus \delta, \theta)\big|_{\delta=0},$$

with the exact Hessian of the (robust) cost in tangent coordinates, not the Gauss-Newton one, so
that problems with nonzero residuals get exact derivatives. `stationary_tangent` is this rule
once, for ICP's poses (`lieax.icp._implicit`) and, through `minimizer_tangents`, which adds the
cost's derivative, for both doors of lieax's Levenberg-Marquardt: `least_squares` (one state,
`with_implicit_derivatives`) and `FactorGraph.solve` (`lieax.factorgraph._implicit`, whose fixed
instances do not move); `local_to_tangents` turns the right-local $\dot\delta$ into JAX tangents
of the solution's leaves (each group leaf's by `leaf_tangent_from_local`). The cost moves by
$\partial f / \partial \theta\,\dot\theta$ (its derivative through $x^*$ vanishes with $g$).
No iteration is unrolled: the rule costs one Hessian ($n$ forward passes over one reverse pass
of the residual) and one $n \times n$ Cholesky solve, and it is linear in $\dot\theta$, so JAX
transposes it for `jax.grad`.
"""

import functools

import jax
import jax.numpy as jnp

from ..autodiff._tangents import (
    leaf_array,
    leaf_tangent_from_local,
    manifold_leaves,
    rplus,
    tangent_dim,
    unflatten_tangents,
)
from ..groups import AbstractManifold, kernels
from ._normal_equations import cholesky_with_fallback, solve_factored
from ._problem import cost


def minimizer_tangents(objective, n, dtype, theta, theta_dot, free=None):
    r"""`(delta_dot, cost_dot)`: the implicit derivative $\dot\delta$ of the minimizer of
    `objective(delta, theta)` at $\delta = 0$ (`stationary_tangent` of its Hessian
    $H = \nabla^2_\delta f$, `n` forward passes over one reverse pass, and of
    $\partial_\theta g\,\dot\theta$) and the cost's $\partial_\theta f\,\dot\theta$ (its
    derivative through the minimizer vanishes with $g$), for `n` tangent coordinates of `dtype`;
    one forward pass gives both $\partial_\theta$ terms."""
    zero = jnp.zeros((n,), dtype=dtype)
    hessian = jax.jacfwd(jax.grad(objective))(zero, theta)
    _, (cost_dot, mixed) = jax.jvp(
        lambda th: jax.value_and_grad(objective)(zero, th), (theta,), (theta_dot,)
    )
    return stationary_tangent(hessian, mixed, free), cost_dot


def stationary_tangent(hessian, mixed, free=None):
    r"""$\dot\delta = -H^{-1}\,\partial_\theta g\,\dot\theta$ for the zero at $\delta = 0$ of a
    gradient $g(\delta, \theta)$, from `hessian` $H = \partial_\delta g$ (`(n, n)`) and `mixed`
    $\partial_\theta g\,\dot\theta$ (`(n,)`). `free` (a boolean mask of the coordinates, or
    `None`) holds the others still: their rows and columns of $H$ become the identity's and their
    $\dot\delta$ is zero. $H$ is symmetrized and solved by `cholesky_with_fallback` (the
    factorization of the dense loop's `solve_spd`, whose regularized fallback gives a singular
    direction, such as a free gauge, no motion, and an indefinite $H$ NaN; `solve_factored` is
    linear in the right side, so JAX transposes it). Used by `least_squares`,
    `FactorGraph.solve` (through `minimizer_tangents`) and ICP."""
    hessian = 0.5 * (hessian + hessian.T)
    if free is not None:
        n = hessian.shape[-1]
        hessian = jnp.where(free[:, None] & free[None, :], hessian, jnp.eye(n, dtype=hessian.dtype))
        mixed = jnp.where(free, mixed, 0.0)
    return -solve_factored(cholesky_with_fallback(hessian), mixed)


def local_to_tangents(leaves, treedef, local):
    """The JAX tangents of a solution's `leaves` (flattened by `manifold_leaves` into
    `treedef`) from their right-local tangents `local` (one array per leaf): a group leaf's by
    `leaf_tangent_from_local` (the tangent carrier), an array's as it is."""
    return treedef.unflatten(
        [
            kernels.element(type(leaf), leaf_tangent_from_local(leaf, d))
            if isinstance(leaf, AbstractManifold)
            else d.astype(leaf.dtype)
            for leaf, d in zip(leaves, local)
        ]
    )


@functools.partial(jax.custom_jvp, nondiff_argnums=(0,))
def with_implicit_derivatives(residual_fn, x_star, cost_star, theta):
    """`(x_star, cost_star)` unchanged, carrying the implicit derivatives with respect to
    `theta = (args, loss)`. `x_star` and `cost_star` are taken as the solution of the problem:
    their own tangents are ignored (the solution does not depend on the start)."""
    return x_star, cost_star


@with_implicit_derivatives.defjvp
def _with_implicit_derivatives_jvp(residual_fn, primals, tangents):
    x_star, cost_star, theta = primals
    _, _, theta_dot = tangents
    leaves, treedef = manifold_leaves(x_star, "solution")
    dtype = jnp.result_type(*(leaf_array(leaf) for leaf in leaves))

    # The Hessian is taken along Exp, whatever retraction the solve used: at a stationary point
    # (zero gradient) the second derivative of the cost along a retraction is the same for every
    # retraction that agrees with Exp to first order (they differ at second order in δ, and that
    # term is multiplied by the gradient), so the derivative of the solution does not depend on it.
    def objective(delta, theta):
        args, loss = theta
        return cost(residual_fn(rplus(x_star, unflatten_tangents(x_star, delta)), args), loss)

    delta_dot, cost_dot = minimizer_tangents(
        objective, tangent_dim(x_star), dtype, theta, theta_dot
    )
    local = jax.tree_util.tree_leaves(unflatten_tangents(x_star, delta_dot))
    x_dot = local_to_tangents(leaves, treedef, local)
    return (x_star, cost_star), (x_dot, jnp.asarray(cost_dot, jnp.result_type(cost_star)))
