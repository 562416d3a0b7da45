"""Tests of `lieax.lstsq._trust_region`, the Levenberg-Marquardt / Gauss-Newton decisions that
`least_squares` and the factor-graph loop share: the damping sequences of Nielsen's and GTSAM's
rules and MINPACK's radius update against hand-computed ones, the gain ratio, the acceptance and
divergence conventions, the precedence of the status codes, that the dense solver's update is the
shared rule, MINPACK's `lmpar` (`_normal_equations.damping_for_radius`), and the order of the
phases of the iteration both loops run (`_iteration.body`)."""

from fractions import Fraction

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from lieax.lstsq import LevenbergMarquardt, Status, _iteration
from lieax.lstsq import _trust_region as trust_region
from lieax.lstsq._normal_equations import damping_for_radius

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
        ratio_in = jnp.asarray(ratio if accept else -1.0)
        kept, state = solver.update(state, ratio_in, finite, jnp.asarray(1.0), jnp.asarray(2.0))
        assert bool(kept) == accept
        damping, factor = trust_region.nielsen(kept, jnp.asarray(ratio), damping, factor)
        damping = jnp.clip(damping, 1e-3, 20.0)
        np.testing.assert_allclose(state[0], damping, rtol=1e-15)
        np.testing.assert_allclose(state[1], factor, rtol=1e-15)
    assert bool(solver.diverged(state, 0.0, 0.0))  # clipped at twice the bound, beyond it


def test_gtsam_preset_update_is_gtsams_rule_and_identity_damping():
    r"""`LevenbergMarquardt.gtsam()` in the dense loop: GTSAM's ×10 / ÷10 from 1e-5 (the same
    `_trust_region.gtsam` the factor graph runs) and the step of $(H + \mu I)$."""
    solver = LevenbergMarquardt.gtsam()
    assert (solver.scaling, solver.damping_update, solver.initial_damping) == (
        "identity", "gtsam", 1e-5
    )  # fmt: skip
    state = solver.init(2, jnp.float64)
    lam = jnp.asarray(1e-5)
    for accept in (False, False, True, False, True, True):
        ratio = jnp.asarray(0.5 if accept else -1.0)
        kept, state = solver.update(state, ratio, jnp.asarray(True), ratio, jnp.asarray(2.0))
        assert bool(kept) == accept
        lam = trust_region.gtsam(kept, lam, 10.0)
        np.testing.assert_allclose(state[0], lam, rtol=1e-15)
    hessian = jnp.array([[4.0, 1.0], [1.0, 3.0]])
    gradient = jnp.array([1.0, -2.0])
    step, _ = solver.step(state, hessian, gradient)
    expected = np.linalg.solve(np.asarray(hessian) + float(state[0]) * np.eye(2), -gradient)
    np.testing.assert_allclose(step, expected, rtol=1e-12)


def test_presets_set_their_libraries_defaults_and_take_changes():
    ceres, minpack_lm = LevenbergMarquardt.ceres(), LevenbergMarquardt.minpack()
    assert (ceres.scaling, ceres.damping_update, ceres.initial_damping) == (
        "jacobi",
        "nielsen",
        1e-4,
    )
    assert (minpack_lm.scaling, minpack_lm.damping_update) == ("minpack", "minpack")
    assert minpack_lm.min_gain_ratio == 1e-4  # lmder's p0001
    changed = LevenbergMarquardt.gtsam(scaling="clipped", damping_update="nielsen")
    assert (changed.scaling, changed.damping_update, changed.max_damping) == (
        "clipped", "nielsen", 1e5
    )  # fmt: skip
    with pytest.raises(ValueError, match="scaling must be one of"):
        LevenbergMarquardt.gtsam(scaling="marquardt")


def minpack(finite, ratio, actual, slope, step_norm, radius, damping, cost=1.0):
    """`trust_region.minpack` on Python numbers, as `(radius, damping)` floats."""
    radius, damping = trust_region.minpack(
        jnp.asarray(finite), jnp.asarray(ratio), jnp.asarray(actual), jnp.asarray(cost),
        jnp.asarray(slope), jnp.asarray(step_norm), jnp.asarray(radius), jnp.asarray(damping),
    )  # fmt: skip
    return float(radius), float(damping)


def test_minpack_radius_update_by_hand():
    # rho >= 3/4: twice the step, half the damping, whatever the radius was
    assert minpack(True, 0.9, 0.5, -1.0, 1.0, 5.0, 4.0) == (2.0, 2.0)
    # 1/4 < rho < 3/4: unchanged, unless the step was Gauss-Newton's (damping 0)
    assert minpack(True, 0.5, 0.5, -1.0, 1.0, 5.0, 4.0) == (5.0, 4.0)
    assert minpack(True, 0.5, 0.5, -1.0, 1.0, 5.0, 0.0) == (2.0, 0.0)
    # rho <= 1/4 with a decrease: tau = 1/2 of min(radius, 10 |D step|)
    assert minpack(True, 0.25, 0.1, -1.0, 1.0, 5.0, 4.0) == (2.5, 8.0)
    assert minpack(True, 0.1, 0.1, -1.0, 0.2, 5.0, 4.0) == (1.0, 8.0)
    # a rise: tau minimizes the quadratic through c, the slope g.step = -1 and the trial cost
    # c - actual along the step, tau = 0.5 * (-1) / (-1 - 0.25) = 0.4 (1/10 at the least)
    radius, damping = minpack(True, -0.5, -0.25, -1.0, 1.0, 5.0, 4.0)
    np.testing.assert_allclose((radius, damping), (2.0, 10.0), rtol=1e-15)
    assert minpack(True, -5.0, -20.0, -1.0, 1.0, 5.0, 4.0) == (0.5, 40.0)
    # a residual grown tenfold (cost 100 times) or not finite: a tenth
    assert minpack(True, -1e3, -99.0, -1e-6, 1.0, 5.0, 4.0) == (0.5, 40.0)
    assert minpack(False, -np.inf, np.nan, -1.0, 1.0, 5.0, 4.0) == (0.5, 40.0)


def test_damping_for_radius_fits_the_step_in_the_radius():
    rng = np.random.default_rng(1)
    jac = rng.normal(size=(12, 5)) * np.array([1.0, 1e-2, 1.0, 1e-4, 0.3])
    matrix, rhs = jac.T @ jac, jac.T @ rng.normal(size=12)
    gauss_newton = np.linalg.norm(np.linalg.solve(matrix, rhs))
    for radius in gauss_newton * np.array([1e-6, 1e-3, 0.1, 0.5, 0.85]):
        for guess in (0.0, 1e-9, 1e3):
            mu = float(damping_for_radius(jnp.asarray(matrix), jnp.asarray(rhs), radius, guess))
            assert mu > 0
            norm = np.linalg.norm(np.linalg.solve(matrix + mu * np.eye(5), rhs))
            assert abs(norm - radius) <= 0.1 * radius, (radius, guess, norm)
    # the Gauss-Newton step when it fits (within 10 %), whatever the guess
    for radius in gauss_newton * np.array([1 / 1.1 + 1e-9, 1.0, 10.0, np.inf]):
        assert float(damping_for_radius(matrix, rhs, radius, 1.0)) == 0.0


def test_damping_for_radius_of_a_singular_system():
    """A variable no residual touches and a repeated column: the regularized Gauss-Newton step
    stands in for the least-squares one, and a damped step still fits the radius."""
    jac = np.array([[1.0, 1.0, 0.0], [2.0, 2.0, 0.0], [0.0, 1.0, 0.0], [3.0, 1.0, 0.0]])
    matrix = jac.T @ jac
    rhs = jac.T @ np.array([1.0, -1.0, 2.0, 0.5])
    regularized = np.linalg.norm(np.linalg.lstsq(jac, np.array([1.0, -1.0, 2.0, 0.5]))[0])
    assert float(damping_for_radius(matrix, rhs, 2 * regularized, 1.0)) == 0.0
    mu = float(damping_for_radius(matrix, rhs, 0.1 * regularized, 1.0))
    norm = np.linalg.norm(np.linalg.solve(matrix + mu * np.eye(3), rhs))
    assert abs(norm - 0.1 * regularized) <= 0.01 * regularized


def test_minpack_damping_update_in_the_solver():
    """`LevenbergMarquardt(damping_update="minpack")`: the first step is Gauss-Newton's and its
    length the first radius; `update` is `trust_region.minpack` on the step it made."""
    solver = LevenbergMarquardt(damping_update="minpack")
    rng = np.random.default_rng(2)
    jac = rng.normal(size=(8, 3)) * np.array([1e3, 1.0, 1e-3])
    hessian, gradient = jnp.asarray(jac.T @ jac), jnp.asarray(jac.T @ rng.normal(size=8))
    step, state = solver.step(solver.init(3, jnp.float64), hessian, gradient)
    np.testing.assert_allclose(step, -np.linalg.solve(jac.T @ jac, gradient), rtol=1e-9)
    damping, radius, scale, step_norm, slope = map(np.asarray, state)
    assert damping == 0.0
    np.testing.assert_allclose(scale, np.linalg.norm(jac, axis=0), rtol=1e-12)
    np.testing.assert_allclose(step_norm, np.linalg.norm(scale * np.asarray(step)), rtol=1e-12)
    np.testing.assert_allclose(radius, step_norm, rtol=1e-15)
    np.testing.assert_allclose(slope, np.asarray(gradient) @ np.asarray(step), rtol=1e-12)
    # a poor step that raised the cost: the radius shrinks and the next step fits it
    kept, state = solver.update(state, jnp.asarray(-2.0), jnp.asarray(True), -0.5, 1.0)
    assert not bool(kept)
    expected, _ = minpack(True, -2.0, -0.5, slope, step_norm, radius, 0.0)
    np.testing.assert_allclose(state[1], expected, rtol=1e-15)
    step, state = solver.step(state, hessian, gradient)
    assert float(state[0]) > 0.0
    assert abs(float(state[3]) - expected) <= 0.1 * expected


def test_iteration_runs_the_phases_in_order():
    calls = []

    def phase(name, result):
        def run(*arguments):
            calls.append((name, arguments))
            return result

        return run

    body = _iteration.body(
        phase("evaluate", "evaluation"),
        phase("decide", "decision"),
        phase("test", ("status", "record")),
        phase("relinearize", ("point", "status after")),
        phase("propose", "next state"),
    )
    assert body("state") == "next state"
    assert calls == [
        ("evaluate", ("state",)),
        ("decide", ("state", "evaluation")),
        ("test", ("state", "evaluation", "decision")),
        ("relinearize", ("state", "evaluation", "decision", "status")),
        ("propose", ("state", "evaluation", "decision", "record", "point", "status after")),
    ]
