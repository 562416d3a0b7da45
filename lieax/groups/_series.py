r"""The trigonometric coefficients of every closed form in lieax, safe at zero angle.

All of SO2, SE2, SO3 and SE3 are written with one family of functions of $s = \theta^2$:

$$g_n(s) = \sum_{k \ge 0} \frac{(-1)^k s^k}{(2k + n)!},$$

so that $g_0 = \cos\theta$, $g_1 = \sin\theta / \theta$, $g_2 = (1 - \cos\theta) / \theta^2$,
$g_3 = (\theta - \sin\theta) / \theta^3$, and in general $g_{n+2} = (1/n! - g_n) / s$.
(These are the coefficients of Solà et al., "A micro Lie theory", eqs. 77, 143, 180, rewritten
so that none divides by $\theta$.)

All are written with the sine and cosine of $\theta/2$ (`_closed`): $g_0 = 1 -
2\sin^2\tfrac\theta2$, $g_1 = 2\sin\tfrac\theta2\cos\tfrac\theta2/\theta$ and $g_2 =
2\,(\sin(\theta/2)/\theta)^2$ cancel nothing and are used at every $s$ (a few ulp). For $n \ge 3$
the closed forms cancel as $\theta \to 0$: below $\theta = 2$ the series is summed, with as many
terms as reach the float64 rounding error there (the series alternates with falling terms, so the
first omitted term, at most $4^K/(2K + n)!$, bounds the error: 11 terms for $g_3$ and $g_4$, 10 for
$g_5$ to $g_8$); above, the recurrence runs from $g_1$ or $g_2$ (it divides by $s \ge 4$, so errors
do not grow). Every value of both branches is finite (the series on a masked $s$), so neither
values nor derivatives of any order are NaN; every $g_n$ of one $s$ shares one sine and one cosine
once XLA merges common subexpressions.

The derivative is closed-form as well, $g_n'(s) = -(g_{n+1}(s) - n\,g_{n+2}(s)) / 2$ (differentiate
the series term by term), and is injected with `jax.custom_jvp`: no derivative of any lieax
Jacobian ever goes through `sin`, `cos` or `sqrt`.
"""

import functools
import math

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax

from .._linalg import horner

_SERIES_LIMIT = 4.0  # s = θ² below which the series of g_n, n >= 3, is used
_TINY_ANGLE = 1e-15  # θ below which g_0 = g_1 = 1 and g_2 = 1/2 to either float's rounding error


@functools.partial(jax.custom_jvp, nondiff_argnums=(0,))
def g(n: int, s: jax.Array) -> jax.Array:
    r"""$g_n(s) = \sum_k (-1)^k s^k / (2k + n)!$ with $s = \theta^2 \ge 0$ (see the module docstring)."""
    # (in `jax.lax` primitives, as `horner`: g is in every closed form, and traced again by
    # every transformation of one)
    s = jnp.asarray(s)
    if n <= 2:
        return _closed(n, s)
    use_series = lax.lt(s, _constant(_SERIES_LIMIT, s))
    s_series = lax.select(use_series, s, lax.full_like(s, 0.0))
    return lax.select(use_series, _series(n, s_series), _closed(n, s))


@g.defjvp
def _g_jvp(n, primals, tangents):
    (s,), (s_dot,) = primals, tangents
    slope = g(n + 1, s) if n == 0 else g(n + 1, s) - n * g(n + 2, s)
    return g(n, s), -0.5 * slope * s_dot


def _closed(n: int, s: jax.Array) -> jax.Array:
    r"""$g_n$ from the sine $h_s$ and cosine $h_c$ of $\theta/2$: $g_0 = 1 - 2h_s^2$,
    $g_1 = 2h_s h_c/\theta$, $g_2 = 2(h_s/\theta)^2$ (the half-angle identities; nothing
    cancels), and for $n \ge 3$ the recurrence $g_{k+2} = (1/k! - g_k)/s$ from $g_1$ or $g_2$
    (accurate where `g` uses it, $s \ge 4$). Below $\theta = 10^{-15}$, $g_0 = 1$, $g_1 = 1$ and
    $g_2 = 1/2$ (their next terms are below either float's rounding error; and $\theta/2$ may be
    subnormal, which XLA flushes to zero); $s$ and $\theta$ are replaced by 1 there, so that every
    value is finite. Every `g_n` of one `s` shares the same sine and cosine (XLA merges common
    subexpressions); derivatives come from `g`'s rule, never from these."""
    theta = lax.sqrt(s)
    tiny = lax.lt(theta, _constant(_TINY_ANGLE, s))
    one = lax.full_like(s, 1.0)
    safe_theta = lax.select(tiny, one, theta)
    half = lax.mul(safe_theta, _constant(0.5, s))
    half_sin, half_cos = lax.sin(half), lax.cos(half)
    if n == 0:
        cosine = lax.sub(one, lax.mul(_constant(2.0, s), lax.mul(half_sin, half_sin)))
        return lax.select(tiny, one, cosine)
    if n % 2:
        value = lax.div(lax.mul(_constant(2.0, s), lax.mul(half_sin, half_cos)), safe_theta)
        value, start = lax.select(tiny, one, value), 1
    else:
        half_sinc = lax.div(half_sin, safe_theta)
        value = lax.mul(_constant(2.0, s), lax.mul(half_sinc, half_sinc))
        value, start = lax.select(tiny, lax.full_like(s, 0.5), value), 2
    safe_s = lax.select(tiny, one, s)
    for m in range(start, n - 1, 2):  # g_{m+2} from g_m
        value = lax.div(lax.sub(_constant(1.0 / math.factorial(m), s), value), safe_s)
    return value


@functools.cache
def _series_coefficients(n: int) -> tuple:
    """$(-1)^k/(2k + n)!$ for $k < K$, $K$ the fewest terms whose first omitted one,
    $4^K/(2K + n)!$, is below $2^{-56} |g_n(4)|$ (an eighth of float64's unit roundoff)."""
    value_at_limit = abs(
        sum((-1) ** k * _SERIES_LIMIT**k / math.factorial(2 * k + n) for k in range(40))
    )
    terms = 1
    while _SERIES_LIMIT**terms / math.factorial(2 * terms + n) >= 2.0**-56 * value_at_limit:
        terms += 1
    return tuple((-1) ** k / math.factorial(2 * k + n) for k in range(terms))


def _series(n: int, s: jax.Array) -> jax.Array:
    return horner(_series_coefficients(n), s)


def _constant(value: float, like: jax.Array) -> np.ndarray:
    """`value` as a scalar of `like`'s dtype (a literal that `jax.lax`'s operations broadcast)."""
    return np.asarray(value, like.dtype)


# ---- the half-angle coefficients of SO(3)'s fused closed forms (Exp with J_r, Log with J_r^{-1}) --
# (here rather than in `_so3` so that the NumPy host forms of `_host` use the same ones)

# θ² below which the fused forms sum Taylor series (7 terms, 9 for D: below 3e-16 relative there
# in float64), above which they use the half-angle closed forms (their cancellation, in g3 and D,
# costs at most 12 eps / θ² = 1e-14 relative at the switch, and nothing in J_r or J_r^{-1}, where
# the coefficient multiplies [ω]×², |[ω]×²| = θ²; float32 loses as much in its own eps)
HALF_ANGLE_SERIES_LIMIT = 0.25
# cos(θ/2), sin(θ/2)/θ and g3 = (θ - sin θ)/θ³ in s = θ²
_HALF_COS = tuple((-1) ** k / (4**k * math.factorial(2 * k)) for k in range(7))
_HALF_SINC = tuple((-1) ** k / (2 * 4**k * math.factorial(2 * k + 1)) for k in range(7))
_G3 = tuple((-1) ** k / math.factorial(2 * k + 3) for k in range(7))
# D(θ) = 1/θ² - cot(θ/2)/(2θ) = Σ_{k≥1} |B_2k| θ^(2k-2) / (2k)! (B_2k the Bernoulli numbers)
_D = (
    1 / 12,
    1 / 720,
    1 / 30240,
    1 / 1209600,
    1 / 47900160,
    691 / 1307674368000,
    1 / 74724249600,
    3617 / 10670622842880000,
    43867 / 5109094217170944000,
)
_D_PRIME = tuple(k * c for k, c in enumerate(_D[1:], start=1))  # dD/ds term by term


def exp_coefficients(s, xp=jnp):
    r"""$(\cos\tfrac\theta2,\ \sin(\theta/2)/\theta,\ g_1,\ g_2,\ g_3)$ of $s = \theta^2$ (shape of
    `s`) from one cosine and one sine (`lieax.groups._so3.exp_and_right_jacobian`'s docstring), in the array namespace
    `xp` (`jax.numpy`, or `numpy` for host-side data)."""
    small = s < HALF_ANGLE_SERIES_LIMIT
    s_safe = xp.where(small, 1.0, s)
    theta = xp.sqrt(s_safe)
    half_cos = xp.where(small, horner(_HALF_COS, s, xp), xp.cos(0.5 * theta))
    half_sinc = xp.where(small, horner(_HALF_SINC, s, xp), xp.sin(0.5 * theta) / theta)
    g1 = 2.0 * half_sinc * half_cos
    g2 = 2.0 * half_sinc * half_sinc
    g3 = xp.where(small, horner(_G3, s, xp), (1.0 - g1) / s_safe)
    return half_cos, half_sinc, g1, g2, g3


def jr_inverse_coefficients(s, half_cos, half_sinc, xp=jnp):
    r"""$(D, D')$ of $s = \theta^2$, $D = 1/\theta^2 - \cot(\theta/2)/(2\theta)$ the coefficient
    of $[\omega]_\times^2$ in $J_r^{-1}$ (`jr_inverse_coefficient`) and $D' = dD/ds$, from
    `exp_coefficients`' $\cos\tfrac\theta2$ and $h = \sin(\theta/2)/\theta$:
    $\cot\tfrac\theta2 = \cos\tfrac\theta2 / (\theta h)$ and
    $\csc^2\tfrac\theta2 = 1/(\theta h)^2$ give
    $D = (1 - \cos\tfrac\theta2 / (2h)) / s$ and
    $D' = -1/s^2 + (\theta\csc^2\tfrac\theta2 + 2\cot\tfrac\theta2)/(8\theta^3)
    = ((1 + 2h\cos\tfrac\theta2)/(8h^2) - 1)/s^2$ (exact at $\pi$, where
    $\cos\tfrac\theta2 = 0$); below $s = 0.25$ their series $\sum_{k\ge1}|B_{2k}|s^{k-1}/(2k)!$
    and its term-by-term derivative (9 terms: below 3e-16 relative; the closed form of $D'$ loses
    $16\epsilon / D' \approx 3\cdot10^{-12}$ relative at the switch, $D'$ multiplies
    $O(\theta^3)$ terms). In the array namespace `xp`."""
    small = s < HALF_ANGLE_SERIES_LIMIT
    s_safe = xp.where(small, 1.0, s)
    d = xp.where(small, horner(_D, s, xp), (1.0 - 0.5 * half_cos / half_sinc) / s_safe)
    closed_prime = ((1.0 + 2.0 * half_sinc * half_cos) / (8.0 * half_sinc**2) - 1.0) / s_safe**2
    return d, xp.where(small, horner(_D_PRIME, s, xp), closed_prime)


def jr_inverse_d_series(s, xp=jnp):
    r"""The series of $D(\theta)$ of `jr_inverse_coefficients` (below `HALF_ANGLE_SERIES_LIMIT`)."""
    return horner(_D, s, xp)
