r"""Derivatives of functions that are computed by iterative algorithms, from the inverse and
implicit function theorems (Ceres Solver's notes, "Using Inverse & Implicit Function Theorems").

- Inverse function theorem: if $y = f(x)$ is hard to compute (an iteration) but its inverse
  $x = g(y)$ is easy, then $Df(x) = (Dg(y))^{-1}$ at $y = f(x)$ (e.g. ECEF → latitude, longitude,
  height, whose inverse is a closed form).
- Implicit function theorem: if $y(x)$ is defined by $F(x, y) = 0$ with $D_y F$ invertible, then
  $Dy(x) = -(D_y F)^{-1} D_x F$ (e.g. a root of a polynomial as a function of its coefficients:
  $Dx(a) = -[1, x, \dots, x^n] / p'(x)$).

`inverse_function_jacobian` and `implicit_jacobian` return these matrices; `with_inverse_derivative`
and `with_implicit_derivative` wrap the iterative function in a `jax.custom_jvp` carrying them, so
that `jax.jacfwd`, `jax.grad`, `jax.vmap` and higher derivatives work without differentiating (or
even being able to differentiate) the iteration. Arguments and values are arrays or pytrees of
arrays; Jacobians are in their flattened coordinates (`jax.flatten_util.ravel_pytree` order),
shape `(size of y, size of x)`.
"""

from collections.abc import Callable

import jax
import jax.numpy as jnp
from jax.flatten_util import ravel_pytree

from .._typing import PyTree


def _flat_function(function, example):
    """`function` on a flat vector in the layout of `example`, returning a flat vector."""
    _, unravel = ravel_pytree(example)
    return lambda flat: ravel_pytree(function(unravel(flat)))[0]


def inverse_function_jacobian(f_inverse: Callable, y: PyTree) -> jax.Array:
    r"""$Df(x) = (D f^{-1}(y))^{-1}$ at $x = f^{-1}(y)$: the Jacobian of a hard function $f$ at the
    point whose image is `y`, from its easy inverse.

    **Arguments:**

    - `f_inverse`: the inverse $g = f^{-1}$, differentiable by JAX.
    - `y`: the value $f(x)$ (array or pytree).

    **Returns:** the matrix $\partial y / \partial x$, shape `(size of y, size of x)`.
    """
    flat_y, _ = ravel_pytree(y)
    jac_inverse = jax.jacfwd(_flat_function(f_inverse, y))(flat_y)
    return jnp.linalg.inv(jac_inverse)


def implicit_jacobian(F: Callable, x: PyTree, y: PyTree) -> jax.Array:
    r"""$Dy(x) = -(D_y F(x, y))^{-1} D_x F(x, y)$ at a solution of $F(x, y) = 0$.

    **Arguments:**

    - `F`: the residual $F(x, y)$, with as many outputs as `y` has entries, differentiable by JAX.
    - `x`, `y`: a point with $F(x, y) = 0$ (arrays or pytrees).

    **Returns:** the matrix $\partial y / \partial x$, shape `(size of y, size of x)`.
    """
    flat_x, unravel_x = ravel_pytree(x)
    flat_y, unravel_y = ravel_pytree(y)

    def flat_residual(fx, fy):
        return ravel_pytree(F(unravel_x(fx), unravel_y(fy)))[0]

    jac_x = jax.jacfwd(flat_residual, 0)(flat_x, flat_y)
    jac_y = jax.jacfwd(flat_residual, 1)(flat_x, flat_y)
    return -jnp.linalg.solve(jac_y, jac_x)


def with_inverse_derivative(f: Callable, f_inverse: Callable) -> Callable:
    r"""`f` with the derivative of the inverse function theorem: $\dot y = (D f^{-1}(y))^{-1} \dot x$.

    `f` itself is never differentiated (it may be a `while_loop`, call the host, ...); `f_inverse`
    is differentiated by JAX at $y = f(x)$. The result is exact to the accuracy to which
    `f_inverse(f(x)) == x` holds.
    """

    @jax.custom_jvp
    def wrapped(x):
        return f(x)

    @wrapped.defjvp
    def _wrapped_jvp(primals, tangents):
        (x,), (x_dot,) = primals, tangents
        y = wrapped(x)
        flat_y, unravel_y = ravel_pytree(y)
        flat_x_dot, _ = ravel_pytree(x_dot)
        jac_inverse = jax.jacfwd(_flat_function(f_inverse, y))(flat_y)
        y_dot = jnp.linalg.solve(jac_inverse, flat_x_dot.astype(flat_y.dtype))
        return y, unravel_y(y_dot)

    return wrapped


def with_implicit_derivative(solve: Callable, F: Callable) -> Callable:
    r"""`solve` (returning $y$ with $F(x, y) = 0$) with the derivative of the implicit function
    theorem: $\dot y = -(D_y F)^{-1} (D_x F\,\dot x)$.

    `solve` itself is never differentiated; `F` is differentiated by JAX at the solution
    ($D_x F\,\dot x$ by one forward pass, $D_y F$ as a square matrix). The derivative is exact to the
    accuracy to which `solve` satisfies $F = 0$.
    """

    @jax.custom_jvp
    def wrapped(x):
        return solve(x)

    @wrapped.defjvp
    def _wrapped_jvp(primals, tangents):
        (x,), (x_dot,) = primals, tangents
        y = wrapped(x)
        flat_y, unravel_y = ravel_pytree(y)
        _, pushed = jax.jvp(lambda xx: ravel_pytree(F(xx, y))[0], (x,), (x_dot,))
        jac_y = jax.jacfwd(lambda fy: ravel_pytree(F(x, unravel_y(fy)))[0])(flat_y)
        return y, unravel_y(-jnp.linalg.solve(jac_y, pushed))

    return wrapped
