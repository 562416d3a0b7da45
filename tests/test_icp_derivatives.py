r"""Derivatives through ICP (`lieax.icp._implicit`): the implicit derivative of the converged pose
against central finite differences of the whole registration, in local coordinates at the
converged pose ($(T(\theta + h\dot\theta) \ominus T^*) - (T(\theta - h\dot\theta) \ominus T^*)$
over $2h$, the matches unchanged at $\pm h$), forward and reverse mode, over motions from the
identity to near π; `vmap`; the runs that did not converge; the bunny when `LIEAX_DATA_DIR` is set.

Every synthetic pair has `N` points (one bucket), so the loops compile once per kind.
"""

import os

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from lieax import SE3, icp
from lieax.lstsq import Cauchy

N = 300
H = 1e-6
TIGHT = {  # converge to the stationary point, to compare with finite differences
    "max_correspondence_distance": 0.4,
    "relative_fitness": 1e-9,
    "relative_rmse": 1e-12,
    "max_iterations": 60,
}
DATA_DIR = os.environ.get("LIEAX_DATA_DIR")


def noisy_pair(rotation_deg, translation, seed=3):
    """A pair with 2 mm of noise along the normals: a minimum with nonzero residuals."""
    return icp.synthetic_pair(
        N, rotation_deg=rotation_deg, translation=translation, noise=0.002, seed=seed
    )


def local(register, star):
    """θ ↦ register(θ).transform ⊖ T*: the pose in local coordinates at the converged one."""
    return lambda *theta: register(*theta).transform.rminus(star)


def central_difference(register, theta, direction, star):
    plus = register(*(x + H * d for x, d in zip(theta, direction)))
    minus = register(*(x - H * d for x, d in zip(theta, direction)))
    np.testing.assert_array_equal(  # the matches must not switch within ±h
        np.asarray(plus.correspondences), np.asarray(minus.correspondences)
    )
    difference = (plus.transform.rminus(star) - minus.transform.rminus(star)) / (2 * H)
    return np.asarray(difference), (plus.inlier_rmse - minus.inlier_rmse) / (2 * H)


def assert_close(derivative, reference, rtol=1e-6):
    derivative, reference = np.asarray(derivative), np.asarray(reference)
    assert np.all(np.isfinite(derivative))
    scale = np.max(np.abs(reference))
    assert scale > 0
    np.testing.assert_allclose(derivative, reference, rtol=0, atol=rtol * scale)


def random_like(*arrays, seed=0):
    rng = np.random.default_rng(seed)
    return tuple(jnp.asarray(rng.normal(size=a.shape)) for a in arrays)


def plane(normals, **options):
    return lambda s, t: icp.point_to_plane(s, t, target_normals=normals, **{**TIGHT, **options})


# ---- the bug this fixes -------------------------------------------------------------------------


@pytest.mark.slow  # the regimes below check jax.jvp and jax.grad, the same rule, at every regime
def test_grad_and_jacfwd_through_point_to_plane_are_the_finite_differences():
    """Before the implicit rule, `jax.grad` failed on the while loop and `jax.jacfwd` silently
    differentiated the unrolled iterations (a component had the wrong sign)."""
    source, target, normals, _ = noisy_pair(8.0, 0.08)
    register = plane(normals)
    star = register(source, target).transform
    loss = lambda s: jnp.sum(register(s, target).transform.translation() ** 2)
    gradient = jax.grad(loss)(source)
    forward = jax.jacfwd(lambda s: register(s, target).transform.rminus(star))(source)
    (direction,) = random_like(source)
    reference, _ = central_difference(lambda s: register(s, target), (source,), (direction,), star)
    assert_close(jnp.einsum("kij,ij->k", forward, direction), reference)
    loss_difference = (loss(source + H * direction) - loss(source - H * direction)) / (2 * H)
    assert float(jnp.sum(gradient * direction)) == pytest.approx(float(loss_difference), rel=1e-6)


# ---- point-to-plane over regimes ----------------------------------------------------------------

REGIMES = {
    "identity": (0.0, 0.0, False),
    "1e-9 from identity": (np.rad2deg(1e-9), 1e-9, False),
    "1e-4 rad": (np.rad2deg(1e-4), 0.0, False),
    "pure translation": (0.0, 0.08, False),
    "pi - 1e-4": (180.0 - np.rad2deg(1e-4), 0.05, True),
    "pi - 1e-6": (180.0 - np.rad2deg(1e-6), 0.05, True),
    "random": (25.0, 0.1, False),
}


@pytest.mark.parametrize("regime", list(REGIMES))
def test_point_to_plane_forward_and_reverse(regime):
    rotation_deg, translation, start_near = REGIMES[regime]
    source, target, normals, truth = noisy_pair(rotation_deg, translation, seed=7)
    # Near π ICP from the identity would not find the minimum: start next to the truth.
    init = truth.rplus(jnp.full(6, 1e-3)) if start_near else None

    def register(s, t, n):
        return icp.point_to_plane(s, t, target_normals=n, init=init, **TIGHT)

    theta = (source, target, normals)
    star = register(*theta)
    assert star.status_name == "CONVERGED" and float(star.inlier_rmse) > 1e-4
    direction = random_like(*theta, seed=1)

    def pose_and_rmse(*th):
        result = register(*th)
        return result.transform.rminus(star.transform), result.inlier_rmse

    _, (pose_dot, rmse_dot) = jax.jvp(pose_and_rmse, theta, direction)
    reference, rmse_reference = central_difference(register, theta, direction, star.transform)
    assert_close(pose_dot, reference)
    assert float(rmse_dot) == pytest.approx(float(rmse_reference), rel=1e-5)
    # Reverse mode: <grad of w·(T ⊖ T*), θ̇> = w·(pose tangent).
    weights = jnp.asarray(np.random.default_rng(2).normal(size=6))
    cotangents = jax.grad(
        lambda *th: jnp.dot(weights, local(register, star.transform)(*th)), argnums=(0, 1, 2)
    )(*theta)
    pushed = sum(jnp.sum(c * d) for c, d in zip(cotangents, direction))
    assert float(pushed) == pytest.approx(float(jnp.dot(weights, pose_dot)), rel=1e-9)


def test_init_has_zero_derivative_and_does_not_move_the_minimum():
    source, target, normals, truth = noisy_pair(8.0, 0.08)
    register = plane(normals)
    at = lambda init: icp.point_to_plane(source, target, target_normals=normals, init=init, **TIGHT)
    star = register(source, target).transform
    start = truth.rplus(jnp.array([0.01, -0.02, 0.0, 0.01, 0.0, -0.01]))
    _, init_dot = jax.jvp(
        lambda p: at(SE3(p)).transform.rminus(star), (start.parameters(),),
        (jnp.asarray(np.random.default_rng(3).normal(size=7)),),
    )  # fmt: skip
    np.testing.assert_array_equal(np.asarray(init_dot), np.zeros(6))
    # The finite-difference view: another start with the same matches, the same minimum.
    moved = at(start.rplus(jnp.full(6, 1e-4))).transform
    assert float(jnp.max(jnp.abs(moved.rminus(at(start).transform)))) < 1e-10


def test_robust_loss_and_its_scale():
    """IRLS weights are differentiated with the residuals; the loss's scale is data too."""
    source, target, normals, _ = noisy_pair(8.0, 0.08)

    def register(s, t, scale):
        return icp.point_to_plane(s, t, target_normals=normals, loss=Cauchy(scale), **TIGHT)

    theta = (source, target, jnp.asarray(0.003))
    star = register(*theta).transform
    direction = (*random_like(source, target, seed=4), jnp.asarray(1.0))
    for mask in ((1, 1, 0), (0, 0, 1)):
        masked = tuple(d * m for d, m in zip(direction, mask))
        _, pose_dot = jax.jvp(local(register, star), theta, masked)
        reference, _ = central_difference(register, theta, masked, star)
        assert_close(pose_dot, reference)


def test_fitness_and_integers_carry_no_derivative():
    source, target, normals, _ = noisy_pair(8.0, 0.08)
    register = plane(normals)
    _, (fitness_dot,) = jax.jvp(
        lambda s: (register(s, target).fitness,), (source,), random_like(source)
    )
    assert float(fitness_dot) == 0.0


# ---- point-to-point -----------------------------------------------------------------------------


def test_point_to_point_forward_and_reverse():
    source, target, _, _ = noisy_pair(8.0, 0.08)

    def register(s, t):
        return icp.point_to_point(s, t, **TIGHT)

    theta = (source, target)
    star = register(*theta)
    assert star.status_name == "CONVERGED"
    direction = random_like(*theta, seed=5)
    _, pose_dot = jax.jvp(local(register, star.transform), theta, direction)
    reference, _ = central_difference(register, theta, direction, star.transform)
    assert_close(pose_dot, reference)
    gradient = jax.grad(lambda s, t: register(s, t).transform.translation()[1], argnums=(0, 1))(
        *theta
    )
    _, translation_dot = jax.jvp(
        lambda s, t: register(s, t).transform.translation()[1], theta, direction
    )
    pushed = sum(jnp.sum(g * d) for g, d in zip(gradient, direction))
    assert float(pushed) == pytest.approx(float(translation_dot), rel=1e-9)


# ---- batches and runs that did not converge -----------------------------------------------------


def test_vmap_gives_each_problem_its_derivative_and_nan_where_undefined():
    pairs = [noisy_pair(8.0, 0.08, seed=s) for s in (3, 4)]
    sources = jnp.stack([p[0] for p in pairs])
    targets = jnp.stack([pairs[0][1], pairs[1][1] + 100.0])  # the second has no overlap
    normals = jnp.stack([p[2] for p in pairs])

    def loss(s, t, n):
        result = icp.point_to_plane(s, t, target_normals=n, throw=False, **TIGHT)
        return jnp.sum(result.transform.translation())

    gradients = jax.vmap(jax.grad(loss))(sources, targets, normals)
    single = jax.grad(loss)(sources[0], targets[0], normals[0])
    np.testing.assert_allclose(np.asarray(gradients[0]), np.asarray(single), rtol=1e-9, atol=1e-12)
    assert np.all(np.isnan(np.asarray(gradients[1])))


def test_a_run_that_did_not_converge_has_no_derivative():
    source, target, normals, _ = noisy_pair(8.0, 0.08)

    def pose(s, throw=True):
        return icp.point_to_plane(
            s, target, target_normals=normals, max_correspondence_distance=0.4, max_iterations=1,
            throw=throw,
        ).transform.parameters()  # fmt: skip

    result = icp.point_to_plane(
        source, target, target_normals=normals, max_correspondence_distance=0.4, max_iterations=1
    )
    assert result.status_name == "MAX_ITERATIONS"
    with pytest.raises(icp.ICPError, match="only at a converged run.*MAX_ITERATIONS"):
        jax.jvp(pose, (source,), random_like(source))
    with pytest.raises(icp.ICPError, match="MAX_ITERATIONS"):
        jax.grad(lambda s: pose(s)[4])(source)
    _, tangent = jax.jvp(lambda s: pose(s, throw=False), (source,), random_like(source))
    assert np.all(np.isnan(np.asarray(tangent)))


def test_estimated_normals_carry_the_target_derivative():
    """With `target_normals=None` the normals are estimated from the target, and move with it."""
    source, target, _, _ = noisy_pair(8.0, 0.08)
    register = lambda s, t: icp.point_to_plane(s, t, **TIGHT)
    star = register(source, target).transform
    direction = random_like(source, target, seed=8)
    _, pose_dot = jax.jvp(local(register, star), (source, target), direction)
    reference, _ = central_difference(register, (source, target), direction, star)
    assert_close(pose_dot, reference)
    pose_of_target = lambda t: local(register, star)(source, t)
    _, target_dot = jax.jvp(pose_of_target, (target,), (direction[1],))
    weights = jnp.asarray(np.random.default_rng(9).normal(size=6))
    cotangent = jax.grad(lambda t: jnp.dot(weights, pose_of_target(t)))(target)
    pushed = float(jnp.sum(cotangent * direction[1]))
    assert pushed == pytest.approx(float(jnp.dot(weights, target_dot)), rel=1e-9)


# ---- real scans ---------------------------------------------------------------------------------


@pytest.mark.skipif(DATA_DIR is None, reason="set LIEAX_DATA_DIR to the shared data")
def test_stanford_bunny():
    """The 2 mm bunny pair from the identity (normals estimated once, then data): derivatives
    with respect to the source and the target against finite differences."""
    data = np.load(os.path.join(DATA_DIR, "clouds", "bunny_045_to_000", "bunny_v0.002.npz"))
    source, target = jnp.asarray(data["source"][::2]), jnp.asarray(data["target"][::2])
    normals = icp.estimate_normals(target, k=30, radius=0.006)

    def register(s, t):
        return icp.point_to_plane(
            s, t, target_normals=normals, max_correspondence_distance=0.01,
            relative_fitness=1e-9, relative_rmse=1e-12, max_iterations=60,
        )  # fmt: skip

    theta = (source, target)
    star = register(*theta)
    assert star.status_name == "CONVERGED"
    direction = tuple(d * 0.01 for d in random_like(*theta, seed=6))  # centimetres
    _, pose_dot = jax.jvp(local(register, star.transform), theta, direction)
    reference, _ = central_difference(register, theta, direction, star.transform)
    assert_close(pose_dot, reference, rtol=1e-5)
