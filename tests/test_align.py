"""`lieax.align` / `SE3.align`: closed-form least-squares alignment of point sets.

- recovers known SE3 and Sim3 transforms to 1e-10 without noise (batched, weighted, rotations up to
  π - 1e-6);
- returns a proper rotation when the best orthogonal matrix is a reflection, and a stationary point
  of the weighted cost with noise (its tangent-space gradient vanishes);
- agrees with GTSAM's `Pose3.Align` / `Similarity3.Align` on noisy data (where gtsam is installed);
- its derivatives with respect to points and weights (implicit function theorem, no SVD derivative)
  match central finite differences, forward equals reverse mode, and they stay finite where the SVD's
  own derivative is not (repeated singular values: a cube's vertices).
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import lieax
from lieax._align import align
from lieax.groups._sim3 import Sim3

SE3 = lieax.SE3


def random_points(rng, count):
    return rng.normal(size=(count, 3)) * np.array([2.0, 1.0, 0.5])


def transforms(with_scale):
    """A batch of 4: identity, small rotation, near π, random (log-scales 0, 1e-4, -0.7, 1.2)."""
    rng = np.random.default_rng(1)
    axis = rng.normal(size=(4, 3))
    axis /= np.linalg.norm(axis, axis=1, keepdims=True)
    angles = np.array([0.0, 1e-4, np.pi - 1e-6, 2.0])[:, None]
    v = rng.normal(size=(4, 3)) * np.array([[0.0], [1.0], [3.0], [1.0]])
    if with_scale:
        sigma = np.array([[0.0], [1e-4], [-0.7], [1.2]])
        return Sim3.exp(jnp.asarray(np.concatenate([v, angles * axis, sigma], axis=1)))
    return SE3.exp(jnp.asarray(np.concatenate([v, angles * axis], axis=1)))


@pytest.mark.parametrize("with_scale", [False, True], ids=["SE3", "Sim3"])
def test_recovers_known_transforms(with_scale):
    rng = np.random.default_rng(0)
    truth = transforms(with_scale)
    b = jnp.asarray(np.stack([random_points(rng, 12) for _ in range(4)]))
    a = jax.vmap(lambda t, pts: t @ pts)(truth, b)
    weights = jnp.asarray(rng.uniform(0.2, 3.0, size=(4, 12)))

    @jax.jit
    def evaluate(a, b, weights):
        return (
            align(a, b, with_scale=with_scale).as_matrix(),
            align(a, b, weights, with_scale=with_scale).as_matrix(),
            align(a[1], b[1], with_scale=with_scale).as_matrix(),  # unbatched
        )

    plain, weighted, single = evaluate(a, b, weights)
    np.testing.assert_allclose(plain, truth.as_matrix(), atol=1e-10)
    np.testing.assert_allclose(weighted, truth.as_matrix(), atol=1e-10)
    np.testing.assert_allclose(single, truth.as_matrix()[1], atol=1e-10)
    result = align(a, b, with_scale=with_scale)
    assert isinstance(result, Sim3 if with_scale else SE3) and result.batch_shape == (4,)


@pytest.mark.skipif(
    not hasattr(SE3, "align"), reason="SE3.align is added by the proposed _se3.py patch"
)
def test_classmethods():
    rng = np.random.default_rng(8)
    b = jnp.asarray(random_points(rng, 10))
    for with_scale in (False, True):
        truth = transforms(with_scale)[3]
        a = truth @ b
        np.testing.assert_allclose(
            SE3.align(a, b, with_scale=with_scale).as_matrix(), truth.as_matrix(), atol=1e-10
        )
    np.testing.assert_allclose(Sim3.align(a, b).as_matrix(), truth.as_matrix(), atol=1e-10)


def test_proper_rotation_and_stationarity():
    """A mirrored cloud: the best orthogonal matrix is a reflection, the result a proper rotation.
    With noise and weights the result is a stationary point of the weighted cost."""
    rng = np.random.default_rng(2)
    b = random_points(rng, 30)
    mirrored = b * np.array([1.0, 1.0, -1.0])
    rotation = align(jnp.asarray(mirrored), jnp.asarray(b)).rotation().as_matrix()
    np.testing.assert_allclose(np.linalg.det(rotation), 1.0, atol=1e-12)
    np.testing.assert_allclose(rotation @ rotation.T, np.eye(3), atol=1e-12)

    truth = transforms(True)[3]
    a = np.asarray(truth @ jnp.asarray(b)) + 0.05 * rng.normal(size=b.shape)
    weights = rng.uniform(0.5, 2.0, size=30)

    def cost(transform):
        residual = jnp.asarray(a) - transform @ jnp.asarray(b)
        return 0.5 * jnp.sum(jnp.asarray(weights) * jnp.sum(residual**2, axis=-1))

    @jax.jit
    def gradients(a, b, weights):
        return [
            lieax.grad(cost)(align(a, b, weights, with_scale=with_scale))
            for with_scale in (False, True)
        ]

    for gradient in gradients(jnp.asarray(a), jnp.asarray(b), jnp.asarray(weights)):
        assert np.max(np.abs(gradient)) < 1e-10, gradient


def test_agrees_with_gtsam():
    gtsam = pytest.importorskip("gtsam")
    rng = np.random.default_rng(3)
    b = random_points(rng, 25)
    for with_scale in (False, True):
        truth = transforms(with_scale)[3]
        a = np.asarray(truth @ jnp.asarray(b)) + 0.05 * rng.normal(size=b.shape)
        result = align(jnp.asarray(a), jnp.asarray(b), with_scale=with_scale)
        if with_scale:
            reference = gtsam.Similarity3.Align([(a[i], b[i]) for i in range(len(a))])
            rotation = reference.rotation().matrix()
            expected = np.eye(4)
            expected[:3, :3] = reference.scale() * rotation
            expected[:3, 3] = reference.scale() * reference.translation()  # t = s · t_gtsam
        else:
            expected = gtsam.Pose3.Align(a.T.copy(), b.T.copy()).matrix()
        np.testing.assert_allclose(result.as_matrix(), expected, atol=1e-10)


def _finite_differences(f, args, step=1e-6):
    """Central differences of `f` (raveled) with respect to each argument (raveled)."""
    base = [np.asarray(x, dtype=np.float64) for x in args]
    perturbed = []
    for i, x in enumerate(base):
        for k in range(x.size):
            for sign in (1.0, -1.0):
                moved = [y.copy() for y in base]
                moved[i].reshape(-1)[k] += sign * step
                perturbed.append(moved)
    stacked = [jnp.asarray(np.stack([p[i] for p in perturbed])) for i in range(len(base))]
    values = np.asarray(jax.jit(jax.vmap(f))(*stacked)).reshape(len(perturbed), -1)
    blocks, start = [], 0
    for x in base:
        pairs = values[start : start + 2 * x.size]
        blocks.append(((pairs[0::2] - pairs[1::2]) / (2 * step)).T)
        start += 2 * x.size
    return blocks


@pytest.mark.parametrize("with_scale", [False, True], ids=["SE3", "Sim3"])
def test_derivatives_match_finite_differences(with_scale):
    """d(matrix)/d(points_a, points_b, weights) by jax.jacfwd and jax.jacrev through the implicit rule
    against central differences, on noisy data (nonzero residuals) and on a cube's vertices, whose
    correlation matrix has three equal singular values (the SVD's derivative is not finite there)."""
    rng = np.random.default_rng(4)
    truth = transforms(with_scale)[3]
    b_noisy = random_points(rng, 7)
    a_noisy = np.asarray(truth @ jnp.asarray(b_noisy)) + 0.1 * rng.normal(size=b_noisy.shape)
    cube = np.array([[x, y, z] for x in (-1.0, 1.0) for y in (-1.0, 1.0) for z in (-1.0, 1.0)])
    a_cube = np.asarray(truth @ jnp.asarray(cube))  # exact: Σ = s R (8/8·I), singular values equal

    def matrix(a, b, w):
        return align(a, b, w, with_scale=with_scale).as_matrix()[:3, :]

    @jax.jit
    def jacobians(a, b, w):
        return jax.jacfwd(matrix, (0, 1, 2))(a, b, w), jax.jacrev(matrix, (0, 1, 2))(a, b, w)

    for name, (a, b) in {"noisy": (a_noisy, b_noisy), "cube": (a_cube, cube)}.items():
        w = rng.uniform(0.5, 2.0, size=len(b))
        forward, reverse = jacobians(jnp.asarray(a), jnp.asarray(b), jnp.asarray(w))
        expected = _finite_differences(matrix, (a, b, w))
        for position, argument in enumerate(("points_a", "points_b", "weights")):
            actual = np.asarray(forward[position]).reshape(12, -1)
            assert np.all(np.isfinite(actual)), (name, argument)
            np.testing.assert_allclose(
                np.asarray(reverse[position]).reshape(12, -1), actual, atol=1e-12
            )
            np.testing.assert_allclose(
                actual, expected[position], atol=2e-7, err_msg=f"{name}: d/d {argument}"
            )
    # the derivative through the SVD itself is wrong (not finite, or garbage from dividing by the
    # rounding error of equal singular values) on the cube: what the rule avoids
    if not with_scale:

        def through_svd(a):
            u, _, vt = jnp.linalg.svd((a - a.mean(0)).T @ (cube - cube.mean(0)))
            return u @ vt

        svd_jacobian = np.asarray(jax.jit(jax.jacfwd(through_svd))(jnp.asarray(a_cube))).reshape(
            9, -1
        )
        rotation_rows = [0, 1, 2, 4, 5, 6, 8, 9, 10]
        expected = _finite_differences(matrix, (a_cube, cube, np.ones(8)))[0][rotation_rows]
        assert not (
            np.all(np.isfinite(svd_jacobian)) and np.allclose(svd_jacobian, expected, atol=1e-3)
        )


def test_local_jacobian_and_errors():
    """`lieax.jacobian` of the alignment (local coordinates of the result) against finite
    differences on matrices; shape errors."""
    rng = np.random.default_rng(6)
    b = random_points(rng, 6)
    a = np.asarray(transforms(False)[3] @ jnp.asarray(b)) + 0.05 * rng.normal(size=b.shape)
    jac = np.asarray(jax.jit(lieax.jacobian(lambda pa: align(pa, jnp.asarray(b))))(jnp.asarray(a)))
    base = np.asarray(align(jnp.asarray(a), jnp.asarray(b)).as_matrix())
    step = 1e-6
    perturbed = np.stack(
        [a + sign * step * e.reshape(a.shape) for e in np.eye(a.size) for sign in (1, -1)]
    )
    matrices = np.asarray(
        jax.jit(jax.vmap(lambda pa: align(pa, jnp.asarray(b)).as_matrix()))(jnp.asarray(perturbed))
    )
    local = []
    for m in matrices:
        delta = np.linalg.solve(base, m) - np.eye(4)
        local.append(
            np.concatenate(
                [
                    delta[:3, 3],
                    0.5
                    * np.array(
                        [
                            delta[2, 1] - delta[1, 2],
                            delta[0, 2] - delta[2, 0],
                            delta[1, 0] - delta[0, 1],
                        ]
                    ),
                ]
            )
        )
    local = np.stack(local)
    fd = ((local[0::2] - local[1::2]) / (2 * step)).T
    np.testing.assert_allclose(jac.reshape(6, -1), fd, atol=1e-7)
    with pytest.raises(ValueError):
        align(jnp.ones((5, 2)), jnp.ones((5, 2)))
    with pytest.raises(ValueError):
        align(jnp.ones((5, 3)), jnp.ones((4, 3)))
