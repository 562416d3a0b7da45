r"""The trigonometric coefficients of every closed form in lieax, safe at zero angle.

All of SO2, SE2, SO3 and SE3 are written with one family of functions of $s = \theta^2$:

$$g_n(s) = \sum_{k \ge 0} \frac{(-1)^k s^k}{(2k + n)!},$$

so that $g_0 = \cos\theta$, $g_1 = \sin\theta / \theta$, $g_2 = (1 - \cos\theta) / \theta^2$,
$g_3 = (\theta - \sin\theta) / \theta^3$, and in general $g_{n+2} = (1/n! - g_n) / s$.
(These are the coefficients of Solà et al., "A micro Lie theory", eqs. 77, 143, 180, rewritten
so that none divides by $\theta$.)

Below $\theta = 2$ the series is summed (16 terms reach the float64 rounding error there); above,
the recurrence runs from $\cos$ and $\sin$ (it divides by $s \ge 4$, so errors do not grow).
Both branches are evaluated on safe inputs and the other one is masked (the "double where"), so
neither values nor derivatives of any order are NaN.

The derivative is closed-form as well, $g_n'(s) = -(g_{n+1}(s) - n\,g_{n+2}(s)) / 2$ (differentiate
the series term by term), and is injected with `jax.custom_jvp`: no derivative of any lieax
Jacobian ever goes through `sin`, `cos` or `sqrt`.
"""

import functools
import math

import jax
import jax.numpy as jnp

_SERIES_LIMIT = 4.0  # s = θ² below which the series is used
_SERIES_TERMS = 16


@functools.partial(jax.custom_jvp, nondiff_argnums=(0,))
def g(n: int, s: jax.Array) -> jax.Array:
    r"""$g_n(s) = \sum_k (-1)^k s^k / (2k + n)!$ with $s = \theta^2 \ge 0$ (see the module docstring)."""
    use_series = s < _SERIES_LIMIT
    s_series = jnp.where(use_series, s, 0.0)
    s_closed = jnp.where(use_series, _SERIES_LIMIT, s)
    return jnp.where(use_series, _series(n, s_series), _closed(n, s_closed))


@g.defjvp
def _g_jvp(n, primals, tangents):
    (s,), (s_dot,) = primals, tangents
    return g(n, s), -0.5 * (g(n + 1, s) - n * g(n + 2, s)) * s_dot


def _series(n: int, s: jax.Array) -> jax.Array:
    coefficients = [(-1) ** k / math.factorial(2 * k + n) for k in range(_SERIES_TERMS)]
    result = jnp.full_like(s, coefficients[-1])
    for c in reversed(coefficients[:-1]):
        result = result * s + c
    return result


def _closed(n: int, s: jax.Array) -> jax.Array:
    theta = jnp.sqrt(s)
    even, odd = jnp.cos(theta), jnp.sin(theta) / theta
    value = even if n % 2 == 0 else odd
    for k in range(n % 2, n - 1, 2):
        value = (1.0 / math.factorial(k) - value) / s
    return value
