"""The coefficient functions `g_n(s) = Σ_k (-1)^k s^k / (2k + n)!` of `lieax.groups._series`.

References, all without mpmath: the series summed exactly in 60-digit `decimal` arithmetic (any s),
the closed forms from `np.cos` / `np.sin` in float64 (moderate s), and the Taylor polynomial
(tiny s). Also: continuity across the switch from series to closed form at s = 4, derivatives
against the term-by-term derivative and finite differences, finiteness of derivatives at 0.
"""

import decimal
import functools
import math

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from registry import SERIES_TOLERANCE

from lieax.groups import _series

g = _series.g
LIMIT = _series._SERIES_LIMIT
ORDERS = tuple(range(9))  # the kernels use g_0 ... g_5; their derivatives g_{n+1}, g_{n+2}

S_GRID = np.array(
    [
        0.0,
        1e-300,
        1e-30,
        1e-16,
        1e-12,
        1e-8,
        1e-5,
        1e-3,
        0.01,
        0.1,
        0.5,
        1.0,
        2.0,
        3.0,
        3.9,
        3.999999,
        4.0,
        4.000001,
        4.1,
        5.0,
        7.0,
        9.0,
        (np.pi / 2) ** 2,
        12.0,
        16.0,
        25.0,
        (np.pi - 1e-6) ** 2,
        np.pi**2,
        20.0,
        30.0,
        39.0,
    ]
)  # s = θ² for θ up to ~2π (Jr⁻¹ of SO3 needs θ < 2π)


def _decimal_series(n, s, derivative=0):
    """The series (or its first or second derivative) in 60-digit arithmetic."""
    with decimal.localcontext() as context:
        context.prec = 60
        s = decimal.Decimal(float(s))
        total, k = decimal.Decimal(0), derivative
        while True:
            falling = math.prod(range(k - derivative + 1, k + 1))  # k (k-1) ... for the derivative
            term = decimal.Decimal((-1) ** k * falling) / math.factorial(2 * k + n)
            term *= s ** (k - derivative) if k > derivative or s != 0 else 1
            total += term
            if k > 10 and abs(term) < decimal.Decimal(10) ** -50 * (1 + abs(total)):
                return float(total)
            k += 1


@functools.cache
def reference(derivative=0):
    return np.array([[_decimal_series(n, s, derivative) for s in S_GRID] for n in ORDERS])


@functools.cache
def lieax_values(dtype=jnp.float64):
    """g_n, g_n', g_n'' on the grid for every order, in one jitted call."""

    def evaluate(s):
        rows = []
        for n in ORDERS:
            single = functools.partial(g, n)
            first = jax.grad(single)
            rows.append(jnp.stack([g(n, s), jax.vmap(first)(s), jax.vmap(jax.grad(first))(s)]))
        return jnp.stack(rows)

    return np.asarray(jax.jit(evaluate)(jnp.asarray(S_GRID, dtype)), dtype=np.float64)


def scale(n):
    """g_n is at most 1/n! in magnitude on s >= 0: compare relative to that."""
    return 1.0 / math.factorial(n)


def tolerance(n, dtype=jnp.float64):
    """Documented absolute accuracy of g_n (and of its derivatives) in `registry.py`."""
    return SERIES_TOLERANCE[n][0 if dtype == jnp.float64 else 1] * scale(n)


@pytest.mark.parametrize("n", ORDERS)
def test_values_against_exact_series(n):
    actual = lieax_values()[n, 0]
    np.testing.assert_allclose(actual, reference()[n], rtol=0, atol=tolerance(n))


@pytest.mark.parametrize("n", ORDERS)
def test_values_against_trigonometric_closed_forms(n):
    """`g_0 = cos θ`, `g_1 = sin θ / θ`, `g_{n+2} = (1/n! - g_n) / s`, in float64 at s in [4, 39]
    (below, the recurrence loses more digits to cancellation than the series)."""
    moderate = S_GRID >= LIMIT
    s = S_GRID[moderate]
    theta = np.sqrt(s)
    closed = np.cos(theta) if n % 2 == 0 else np.sin(theta) / theta
    for k in range(n % 2, n - 1, 2):
        closed = (1.0 / math.factorial(k) - closed) / s
    np.testing.assert_allclose(lieax_values()[n, 0][moderate], closed, rtol=0, atol=tolerance(n))


@pytest.mark.parametrize("n", ORDERS)
def test_values_against_taylor_at_tiny_s(n):
    tiny = S_GRID <= 1e-5
    s = S_GRID[tiny]
    taylor = 1 / math.factorial(n) - s / math.factorial(n + 2) + s**2 / math.factorial(n + 4)
    np.testing.assert_allclose(lieax_values()[n, 0][tiny], taylor, rtol=1e-15, atol=0)


@pytest.mark.parametrize("n", ORDERS)
def test_derivatives_against_exact_series(n):
    first, second = lieax_values()[n, 1], lieax_values()[n, 2]
    np.testing.assert_allclose(first, reference(1)[n], rtol=0, atol=tolerance(n))
    np.testing.assert_allclose(second, reference(2)[n], rtol=0, atol=tolerance(n))
    # at zero: g_n'(0) = -1/(n+2)!, g_n''(0) = 2/(n+4)!
    assert first[0] == pytest.approx(-1 / math.factorial(n + 2), rel=1e-15)
    assert second[0] == pytest.approx(2 / math.factorial(n + 4), rel=1e-15)


@pytest.mark.parametrize("n", ORDERS)
def test_derivative_against_finite_differences(n):
    h = 1e-5 * np.maximum(1.0, S_GRID)
    evaluate = jax.jit(lambda s: g(n, s))
    fd = (np.asarray(evaluate(S_GRID + h)) - np.asarray(evaluate(S_GRID - h))) / (2 * h)
    # g_n is defined on s = θ² >= 0: one-sided, second-order differences where s - h < 0
    near_zero = S_GRID < h
    one_sided = (
        -3 * np.asarray(evaluate(S_GRID))
        + 4 * np.asarray(evaluate(S_GRID + h))
        - np.asarray(evaluate(S_GRID + 2 * h))
    ) / (2 * h)
    fd = np.where(near_zero, one_sided, fd)
    np.testing.assert_allclose(lieax_values()[n, 1], fd, rtol=0, atol=1e-9 * scale(n))


@pytest.mark.parametrize("n", ORDERS)
def test_continuity_at_the_branch_switch(n):
    """Values and derivatives agree on both sides of s = 4 (series below, closed form above)."""
    s = jnp.asarray([np.nextafter(LIMIT, 0.0), LIMIT, np.nextafter(LIMIT, np.inf)])
    values = np.asarray(jax.vmap(functools.partial(g, n))(s))
    derivatives = np.asarray(jax.vmap(jax.grad(functools.partial(g, n)))(s))
    exact = _decimal_series(n, LIMIT)
    np.testing.assert_allclose(values, exact, rtol=0, atol=tolerance(n))
    np.testing.assert_allclose(derivatives, _decimal_series(n, LIMIT, 1), rtol=0, atol=tolerance(n))


def test_nothing_is_nan_for_any_order_of_derivative():
    s = jnp.asarray([0.0, 1e-300, 4.0, 39.0])
    third = jax.vmap(jax.grad(jax.grad(jax.grad(functools.partial(g, 3)))))(s)
    assert np.all(np.isfinite(third))


def test_batch_shapes():
    s = jnp.linspace(0.0, 30.0, 24).reshape(2, 3, 4)
    for n in (0, 3):
        value = g(n, s)
        assert value.shape == (2, 3, 4)
        np.testing.assert_allclose(
            value, np.vectorize(functools.partial(_decimal_series, n))(s), atol=1e-15
        )


def test_float32():
    values32 = lieax_values(jnp.float32)
    s32 = S_GRID.astype(np.float32).astype(np.float64)  # the float32 inputs, exactly
    for n in ORDERS:
        exact = np.array([_decimal_series(n, s) for s in s32])
        atol = tolerance(n, jnp.float32)
        np.testing.assert_allclose(values32[n, 0], exact, rtol=0, atol=atol, err_msg=f"g_{n}")
        exact_first = np.array([_decimal_series(n, s, 1) for s in s32])
        np.testing.assert_allclose(
            values32[n, 1], exact_first, rtol=0, atol=atol, err_msg=f"g_{n}'"
        )


@pytest.mark.parametrize("dtype", [jnp.float64, jnp.float32], ids=["float64", "float32"])
def test_tiny_angles_under_jit(dtype):
    """At θ down to the smallest normal number, `g(n, θ²)` inside `jit` (where XLA rewrites
    `sqrt(θ·θ)` to `|θ|`, and flushes a subnormal `θ/2` to zero) is the Taylor value, and its
    derivative by θ is finite."""
    finfo = np.finfo(dtype)
    theta = jnp.asarray([finfo.tiny, 1e-30, 1e-16, 1e-15, 2e-15, 1e-9], dtype)
    for n in ORDERS:
        of_angle = functools.partial(lambda n, t: g(n, t * t), n)
        values = jax.jit(of_angle)(theta)
        taylor = 1 / math.factorial(n) - np.asarray(theta, np.float64) ** 2 / math.factorial(n + 2)
        np.testing.assert_allclose(values, taylor, rtol=2 * finfo.eps, atol=0)
        slopes = jax.jit(jax.vmap(jax.grad(of_angle)))(theta)
        assert np.all(np.isfinite(slopes))
