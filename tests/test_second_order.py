"""Second derivatives of every registered group, float64: Hessians in tangent coordinates through
`exp` (at every regime's tangent, the identity included), `compose`, `act` and `log`, against central finite differences of the gradient, at every regime of the registry
(identity and 1e-9 from it included, where the Taylor branches are taken); and derivatives with
respect to the raw parameters (`G(params).normalize()`) against finite differences along them.

One jitted program per group evaluates every regime (`results`, cached).
"""

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from _stacked import at_zero_and_steps
from registry import GROUP_IDS, GROUPS, random_points, random_tangents, regime_tangents, regimes_for

STEP = 1e-5  # central differences of the gradient: error ~ STEP² |∇³c| + rounding / STEP
RAW_STEP = 1e-6
TOLERANCE = 1e-6  # |H - H_fd| <= TOLERANCE * max(1, |H_fd|)
# Sim3's and SE23's rules are `_generic.local_rules`, the code SE3's case runs by default, and their
# first derivatives at every regime are in test_jacobians.py: their cases (~25 s each) are slow.
SPECS = [
    pytest.param(
        spec, id=spec.name, marks=[pytest.mark.slow] if spec.name in ("Sim3", "SE23") else []
    )
    for spec in GROUPS
]


def cost(spec, delta, xi, y, p):
    r"""$c(\delta) = |Z p|^2 + \sum \sin \mathrm{Log}\,Z$, $Z = Y\,\mathrm{Exp}(\xi + \delta)$:
    through `exp`, `compose`, `act` and `log` (Y random, so that Log is away from π)."""
    z = y @ spec.cls.exp(xi + delta)
    return jnp.sum((z @ p) ** 2) + jnp.sum(jnp.sin(z.log()))


@functools.cache
def results(name):
    """Per regime: the gradient and Hessian at δ = 0 and central differences of the gradient; on
    the raw parameters of `X = Exp(ξ)`: `jax.jacfwd`, `jax.jacrev` and central differences of
    `G(params).normalize() @ p`."""
    spec = GROUPS[GROUP_IDS.index(name)]
    G = spec.cls
    regimes = regimes_for(spec)
    xis = regime_tangents(spec)
    count = len(xis)
    etas = random_tangents(spec, count, seed=21)
    points = random_points(spec, count, seed=22)

    def one(xi, eta, p):
        c = functools.partial(cost, spec, xi=xi, y=G.exp(eta), p=p)
        gradient = jax.grad(c)
        zero = jnp.zeros(spec.dim)
        gradient_at_zero, plus, minus = at_zero_and_steps(gradient, STEP * jnp.eye(spec.dim))

        def on_raw(params):
            return G(params).normalize() @ p

        params = G.exp(xi).parameters()
        raw_shifts = RAW_STEP * jnp.eye(G.parameters_dim)
        raw_plus, raw_minus = jnp.split(
            jax.vmap(lambda d: on_raw(params + d))(jnp.concatenate([raw_shifts, -raw_shifts])), 2
        )
        return {
            "gradient": gradient_at_zero,
            "hessian": jax.hessian(c)(zero),
            "hessian_fd": (plus - minus).T / (2.0 * STEP),
            "raw_jacfwd": jax.jacfwd(on_raw)(params),
            "raw_jacrev": jax.jacrev(on_raw)(params),
            "raw_fd": (raw_plus - raw_minus).T / (2.0 * RAW_STEP),
        }

    out = jax.jit(jax.vmap(one))(jnp.asarray(xis), jnp.asarray(etas), jnp.asarray(points))
    return jax.tree_util.tree_map(np.asarray, out), regimes


@pytest.mark.parametrize("spec", SPECS)
def test_hessian_matches_finite_differences(spec):
    """The Hessian of `cost` (forward over reverse mode through the groups' rules) is symmetric and
    matches central differences of its gradient; both finite at every regime."""
    out, regimes = results(spec.name)
    for index, regime in enumerate(regimes):
        gradient, hessian, fd = (out[key][index] for key in ("gradient", "hessian", "hessian_fd"))
        what = f"{spec} at {regime}"
        assert np.all(np.isfinite(gradient)) and np.all(np.isfinite(hessian)), what
        scale = max(1.0, np.abs(fd).max())
        np.testing.assert_allclose(hessian, hessian.T, atol=1e-10 * scale, err_msg=what)
        np.testing.assert_allclose(hessian, fd, rtol=0, atol=TOLERANCE * scale, err_msg=what)


@pytest.mark.parametrize("spec", SPECS)
def test_raw_parameter_derivatives(spec):
    """Derivatives with respect to raw parameters (`G(params)`, then `normalize`) match central
    differences along them, and `jax.jacrev` matches `jax.jacfwd`, at every regime."""
    out, regimes = results(spec.name)
    for index, regime in enumerate(regimes):
        forward, reverse, fd = (out[key][index] for key in ("raw_jacfwd", "raw_jacrev", "raw_fd"))
        what = f"{spec} raw parameters at {regime}"
        scale = max(1.0, np.abs(fd).max())
        np.testing.assert_allclose(forward, fd, rtol=0, atol=1e-8 * scale, err_msg=what)
        np.testing.assert_allclose(reverse, forward, rtol=0, atol=1e-12 * scale, err_msg=what)
