r"""`inverse_function_jacobian` / `implicit_jacobian` and their `custom_jvp` wrappers, on the two
examples of Ceres' notes: ECEF → (latitude, longitude, height) by a `while_loop` iteration
(whose inverse is a closed form), and the roots of a polynomial as functions of its coefficients
(Newton's method; $Dx(a) = -[1, x, \dots, x^n] / p'(x)$). Everything is checked against central
finite differences of the iterative functions themselves; `jax.jacrev` works although the
iterations (`lax.while_loop`) cannot be reverse-differentiated.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from jax import lax

from lieax.autodiff._implicit import (
    implicit_jacobian,
    inverse_function_jacobian,
    with_implicit_derivative,
    with_inverse_derivative,
)

# WGS84
A = 6378137.0
F_FLAT = 1.0 / 298.257223563
E2 = F_FLAT * (2.0 - F_FLAT)


def lla_to_ecef(lla):
    r"""$(\phi, \lambda, h) \mapsto (X, Y, Z)$ (Ceres' notes; radians and metres)."""
    lat, lon, h = lla[0], lla[1], lla[2]
    chi = jnp.sqrt(1.0 - E2 * jnp.sin(lat) ** 2)
    return jnp.stack(
        [
            (A / chi + h) * jnp.cos(lat) * jnp.cos(lon),
            (A / chi + h) * jnp.cos(lat) * jnp.sin(lon),
            (A * (1.0 - E2) / chi + h) * jnp.sin(lat),
        ]
    )


def ecef_to_lla(xyz):
    """The iterative inverse: fixed point on the latitude, run by a `while_loop` to convergence."""
    x, y, z = xyz[0], xyz[1], xyz[2]
    lon = jnp.arctan2(y, x)
    p = jnp.sqrt(x * x + y * y)

    def height(lat):
        n = A / jnp.sqrt(1.0 - E2 * jnp.sin(lat) ** 2)
        return p / jnp.cos(lat) - n, n

    def step(state):
        lat, _, k = state
        h, n = height(lat)
        new = jnp.arctan2(z, p * (1.0 - E2 * n / (n + h)))
        return new, jnp.abs(new - lat), k + 1

    lat0 = jnp.arctan2(z, p * (1.0 - E2))
    lat, _, _ = lax.while_loop(lambda s: (s[1] > 1e-15) & (s[2] < 50), step, (lat0, jnp.inf, 0))
    return jnp.stack([lat, lon, height(lat)[0]])


LLA_POINTS = np.array(
    [[0.5, 1.2, 120.0], [-0.9, -2.5, 3500.0], [1.3, 0.1, -50.0], [0.01, 3.0, 8.0e5]]
)


def central_differences(f, x, step):
    x = np.asarray(x, dtype=np.float64)
    columns = []
    for k in range(x.size):
        e = np.zeros_like(x)
        e.reshape(-1)[k] = step
        columns.append((np.asarray(f(x + e)) - np.asarray(f(x - e))).reshape(-1) / (2 * step))
    return np.stack(columns, axis=1)


def test_ecef_to_lla_by_inverse_function_theorem():
    ecef_to_lla_jit = jax.jit(ecef_to_lla)
    differentiable = jax.jit(with_inverse_derivative(ecef_to_lla, lla_to_ecef))
    jacobians = jax.jit(
        lambda x: (
            jax.jacfwd(with_inverse_derivative(ecef_to_lla, lla_to_ecef))(x),
            jax.jacrev(with_inverse_derivative(ecef_to_lla, lla_to_ecef))(x),
        )
    )
    helper = jax.jit(lambda lla: inverse_function_jacobian(lla_to_ecef, lla))
    for lla in LLA_POINTS:
        xyz = lla_to_ecef(jnp.asarray(lla))
        np.testing.assert_allclose(ecef_to_lla_jit(xyz), lla, rtol=1e-12, atol=1e-8)
        np.testing.assert_allclose(differentiable(xyz), ecef_to_lla_jit(xyz), rtol=0, atol=0)
        fd = central_differences(ecef_to_lla_jit, xyz, step=1.0)  # 1 m: truncation ~ (1/R)³
        jac = np.asarray(helper(ecef_to_lla_jit(xyz)))
        scale = np.abs(fd).max(axis=1, keepdims=True)  # rows in radians/m and m/m
        assert np.all(np.abs(jac - fd) <= 1e-7 * scale), (jac, fd)
        forward, reverse = jacobians(xyz)
        for other in (forward, reverse):
            assert np.all(np.abs(np.asarray(other) - jac) <= 1e-12 * scale)
    # batched under vmap, and the plain iteration cannot be reverse-differentiated
    batch = jax.vmap(lla_to_ecef)(jnp.asarray(LLA_POINTS))
    batched = jax.jit(jax.vmap(jax.jacrev(with_inverse_derivative(ecef_to_lla, lla_to_ecef))))(
        batch
    )
    assert batched.shape == (4, 3, 3) and np.all(np.isfinite(batched))
    with pytest.raises(ValueError):
        jax.jacrev(ecef_to_lla)(batch[0])


def polynomial(coefficients, x):
    r"""$p(x) = \sum_k a_k x^k$."""
    return jnp.sum(coefficients * x ** jnp.arange(coefficients.shape[-1]))


def newton_root(coefficients, x0):
    """A real root of the polynomial by Newton's method from `x0` (a `while_loop`)."""
    derivative = jax.grad(polynomial, argnums=1)

    def step(state):
        x, _, k = state
        new = x - polynomial(coefficients, x) / derivative(coefficients, x)
        return new, jnp.abs(new - x), k + 1

    root, _, _ = lax.while_loop(
        lambda s: (s[1] > 1e-15 * (1 + jnp.abs(s[0]))) & (s[2] < 100), step, (x0, jnp.inf, 0)
    )
    return root


def test_polynomial_roots_by_implicit_function_theorem():
    """Roots of $(x - 1)(x + 2)(x - 3.5)(x^2 + 1)$ (three real roots) from three starting points."""
    coefficients = jnp.asarray(np.polynomial.polynomial.polyfromroots([1.0, -2.0, 3.5]))
    coefficients = jnp.asarray(np.polynomial.polynomial.polymul(coefficients, [1.0, 0.0, 1.0]))
    residual = lambda a, x: polynomial(a, x)

    @jax.jit
    def evaluate(a, x0):
        solve = with_implicit_derivative(lambda a: newton_root(a, x0), residual)
        root = solve(a)
        return root, jax.grad(solve)(a), jax.jacfwd(solve)(a), implicit_jacobian(residual, a, root)

    for x0, expected_root in ((0.8, 1.0), (-3.0, -2.0), (5.0, 3.5)):
        root, gradient, forward, helper = evaluate(coefficients, jnp.asarray(x0))
        np.testing.assert_allclose(root, expected_root, rtol=1e-13)
        powers = np.asarray(root) ** np.arange(coefficients.shape[0])
        slope = np.polynomial.polynomial.polyval(
            np.asarray(root), np.polynomial.polynomial.polyder(coefficients)
        )
        ceres = -powers / slope  # Dx(a) = -[1, x, ..., x^n] / p'(x)
        np.testing.assert_allclose(gradient, ceres, rtol=1e-12)
        np.testing.assert_allclose(forward, ceres, rtol=1e-12)
        np.testing.assert_allclose(np.asarray(helper).reshape(-1), ceres, rtol=1e-12)
        fd = central_differences(
            jax.jit(lambda a, x0=x0: newton_root(a, jnp.asarray(x0))), coefficients, 1e-6
        )
        np.testing.assert_allclose(fd.reshape(-1), ceres, rtol=1e-6, atol=1e-9)


def test_implicit_system_with_pytrees():
    r"""A 2D system $F(x, y) = (y_0^2 + y_1^2 - x_r,\ y_1 - x_s y_0)$ (circle ∩ line), `x` a dict:
    the helper and the wrapper against finite differences."""

    def residual(x, y):
        return jnp.stack([y[0] ** 2 + y[1] ** 2 - x["r"], y[1] - x["s"] * y[0]])

    def solve(x):  # the intersection with y_0 > 0, in closed form for the test
        y0 = jnp.sqrt(x["r"] / (1.0 + x["s"] ** 2))
        return jnp.stack([y0, x["s"] * y0])

    @jax.jit
    def evaluate(x):
        wrapped = with_implicit_derivative(solve, residual)
        return (
            implicit_jacobian(residual, x, solve(x)),
            jax.jacfwd(solve)(x),
            jax.jacrev(wrapped)(x),
        )

    jac, direct, through_wrapper = evaluate({"r": jnp.asarray(2.0), "s": jnp.asarray(0.7)})
    expected = np.stack([np.asarray(direct[k]) for k in ("r", "s")], axis=1)  # ravel order: r, s
    np.testing.assert_allclose(jac, expected, rtol=1e-12)
    np.testing.assert_allclose(
        np.stack([through_wrapper[k] for k in ("r", "s")], axis=1), expected, rtol=1e-12
    )
