"""Tests of `lieax.lstsq._trust_region`, the Levenberg-Marquardt / Gauss-Newton decisions that
`least_squares` and the factor-graph loop share: the damping sequences of Nielsen's and GTSAM's
rules against hand-computed ones, the gain ratio, the acceptance and divergence conventions, the
precedence of the status codes, and that the dense solver's update is the shared rule."""

from fractions import Fraction

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from lieax.lstsq import LevenbergMarquardt, Status
from lieax.lstsq import _trust_region as trust_region

jax.config.update("jax_enable_x64", True)


def run(rule, steps, damping, factor):
    """The `(damping, factor)` after each `(accept, gain_ratio)` of `steps`."""
    sequence = []
    for accept, ratio in steps:
        damping, factor = rule(jnp.asarray(accept), jnp.asarray(ratio), damping, factor)
        sequence.append((float(damping), float(factor)))
    return sequence


def test_nielsen_sequence_by_hand():
    # mu <- mu * max(1/3, 1 - (2 rho - 1)^3), nu <- 2 when taken; mu <- nu mu, nu <- 2 nu when not
    steps = [(False, -1.0), (False, 0.0), (True, 1.0), (True, 0.5), (True, 0.25), (False, 0.9)]
    shrink = 1 - (2 * Fraction(1, 4) - 1) ** 3  # 9/8: a poor step raises the damping
    expected = [
        (2, 4),  # rejected: times nu = 2, nu doubles
        (8, 8),  # rejected: times nu = 4
        (Fraction(8, 3), 2),  # rho = 1: the largest decrease, a third
        (Fraction(8, 3), 2),  # rho = 1/2: 1 - 0 = 1, unchanged
        (Fraction(8, 3) * shrink, 2),  # rho = 1/4
        (Fraction(8, 3) * shrink * 2, 4),  # rejected again: nu restarts from 2
    ]
    got = run(trust_region.nielsen, steps, jnp.asarray(1.0), jnp.asarray(2.0))
    np.testing.assert_allclose(got, [(float(a), float(b)) for a, b in expected], rtol=1e-15)


def test_nielsen_shrink_is_bounded_by_a_third():
    ratios = jnp.linspace(-2.0, 3.0, 101)
    damping, factor = trust_region.nielsen(jnp.ones_like(ratios, bool), ratios, 3.0, 8.0)
    assert np.all(np.asarray(damping) >= 1.0 - 1e-15)
    np.testing.assert_array_equal(factor, 2.0)
    np.testing.assert_allclose(damping[ratios >= 1.0], 1.0, rtol=1e-15)


def test_gtsam_sequence_by_hand():
    # GTSAM 4.3 (fixed lambda factor 10): divide on success, multiply on failure
    lam, sequence = jnp.asarray(1e-5), []
    for accept in (False, False, True, False, True, True):
        lam = trust_region.gtsam(jnp.asarray(accept), lam, 10.0)
        sequence.append(float(lam))
    np.testing.assert_allclose(sequence, [1e-4, 1e-3, 1e-4, 1e-3, 1e-4, 1e-5], rtol=1e-14)


def test_gain_ratio():
    np.testing.assert_allclose(trust_region.gain_ratio(3.0, 4.0), 0.75)
    np.testing.assert_allclose(trust_region.gain_ratio(-1.0, 2.0), -0.5)
    # a non-positive prediction divides by one: the loops decide what it means
    np.testing.assert_allclose(trust_region.gain_ratio(3.0, 0.0), 3.0)
    np.testing.assert_allclose(trust_region.gain_ratio(3.0, -2.0), 3.0)


def test_acceptance_and_divergence_conventions():
    # MINPACK keeps a step whose ratio equals the threshold, GTSAM and Ceres do not
    assert bool(trust_region.accepts(1e-3, 1e-3, inclusive=True))
    assert not bool(trust_region.accepts(1e-3, 1e-3, inclusive=False))
    assert bool(trust_region.accepts(2e-3, 1e-3, inclusive=False))
    assert not bool(trust_region.accepts(0.0, 1e-3, inclusive=True))
    # GTSAM gives up at lambda >= lambdaUpperBound; least_squares (Ceres) beyond the bound
    assert bool(trust_region.damping_exhausted(1e5, 1e5, inclusive=True))
    assert not bool(trust_region.damping_exhausted(1e5, 1e5, inclusive=False))
    assert bool(trust_region.damping_exhausted(2e5, 1e5, inclusive=False))
    # Gauss-Newton: the cost beyond a multiple of the initial one
    assert bool(trust_region.cost_diverged(1e7, 2.0, 1e6))
    assert not bool(trust_region.cost_diverged(2e6, 2.0, 1e6))


def test_status_precedence():
    flags = np.array(np.meshgrid(*[[False, True]] * 4, indexing="ij")).reshape(4, -1)
    codes = np.asarray(jax.vmap(trust_region.status)(*map(jnp.asarray, flags)))
    assert codes.dtype == np.int32
    order = [Status.NONFINITE, Status.CONVERGED, Status.DIVERGED, Status.MAX_ITERATIONS]
    for flag, code in zip(flags.T, codes):
        assert code == next((s for s, f in zip(order, flag) if f), Status.RUNNING)


@pytest.mark.parametrize("scaling", ["minpack", "jacobi"])
def test_levenberg_marquardt_update_is_nielsen_clipped(scaling):
    solver = LevenbergMarquardt(scaling=scaling, min_damping=1e-3, max_damping=10.0)
    state = solver.init(2, jnp.float64)
    damping, factor = state[0], state[1]
    for accept, ratio in [(True, 1.0), (True, 1.0), (False, 0.0), (True, 0.5)] + [(False, 0.0)] * 6:
        finite = jnp.asarray(True)
        kept, state = solver.update(state, jnp.asarray(ratio if accept else -1.0), finite)
        assert bool(kept) == accept
        damping, factor = trust_region.nielsen(kept, jnp.asarray(ratio), damping, factor)
        damping = jnp.clip(damping, 1e-3, 20.0)
        np.testing.assert_allclose(state[0], damping, rtol=1e-15)
        np.testing.assert_allclose(state[1], factor, rtol=1e-15)
    assert bool(solver.diverged(state, 0.0, 0.0))  # clipped at twice the bound, beyond it
