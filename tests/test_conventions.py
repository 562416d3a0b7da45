"""`lieax.conventions`: converters round-trip, satisfy their defining identities, and (where gtsam
is installed) turn lieax's values and Jacobians into GTSAM's `Pose3`, `Rot3`, `Similarity3` and
`Unit3` ones: `Expmap`, `Logmap`, `AdjointMap`, `ExpmapDerivative`, `LogmapDerivative`, `compose`,
`between`, `transformFrom`, `rotate`, `errorVector`, `basis`, `localCoordinates`. Only the GTSAM
comparisons are skipped without gtsam.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.linalg

import lieax
from lieax import conventions as cv
from lieax.groups import _base
from lieax.groups._s2 import S2
from lieax.groups._sim3 import Sim3

SE3, SO3 = lieax.SE3, lieax.SO3
MANIFOLD_PATCH = hasattr(_base, "AbstractManifold")

RNG = np.random.default_rng(7)
SE3_TANGENTS = np.concatenate([RNG.normal(size=(4, 3)), RNG.normal(size=(4, 3))], axis=1)
SE3_TANGENTS[0, 3:] = 0.0  # pure translation
SE3_TANGENTS[1, 3:] *= (np.pi - 1e-3) / np.linalg.norm(SE3_TANGENTS[1, 3:])  # near π
SIM3_TANGENTS = np.concatenate([SE3_TANGENTS, RNG.uniform(-1.0, 1.0, size=(4, 1))], axis=1)
POINTS = RNG.normal(size=(4, 3))
DIRECTIONS = RNG.normal(size=(4, 3))
DIRECTIONS /= np.linalg.norm(DIRECTIONS, axis=1, keepdims=True)


def test_round_trips():
    xi6, xi7 = jnp.asarray(SE3_TANGENTS), jnp.asarray(SIM3_TANGENTS)
    np.testing.assert_array_equal(cv.se3_tangent_from_gtsam(cv.se3_tangent_to_gtsam(xi6)), xi6)
    np.testing.assert_array_equal(cv.se3_tangent_to_gtsam(xi6)[..., :3], xi6[..., 3:])
    np.testing.assert_array_equal(cv.sim3_tangent_from_gtsam(cv.sim3_tangent_to_gtsam(xi7)), xi7)
    np.testing.assert_array_equal(cv.sim3_tangent_to_gtsam(xi7)[..., 6], xi7[..., 6])
    jac = jnp.asarray(RNG.normal(size=(4, 6, 6)))
    np.testing.assert_array_equal(cv.se3_jacobian_from_gtsam(cv.se3_jacobian_to_gtsam(jac)), jac)
    jac_points = jnp.asarray(RNG.normal(size=(3, 7)))
    np.testing.assert_array_equal(
        cv.sim3_jacobian_from_gtsam(cv.sim3_jacobian_to_gtsam(jac_points, rows=False), rows=False),
        jac_points,
    )
    with pytest.raises(ValueError):
        cv.se3_jacobian_to_gtsam(jnp.zeros((3, 6)))  # rows are not a tangent
    q = SO3.exp(xi6[:, 3:]).wxyz
    np.testing.assert_array_equal(cv.xyzw_to_wxyz(cv.wxyz_to_xyzw(q)), q)
    np.testing.assert_array_equal(cv.wxyz_to_xyzw(q)[..., 3], q[..., 0])
    poses = SE3.exp(xi6)
    ros = cv.se3_to_xyz_xyzw(poses)
    np.testing.assert_allclose(ros[..., :3], poses.translation())
    np.testing.assert_allclose(cv.se3_from_xyz_xyzw(ros).as_matrix(), poses.as_matrix(), atol=1e-15)
    sim = Sim3.exp(xi7)
    np.testing.assert_allclose(
        cv.sim3_from_gtsam(*cv.sim3_to_gtsam(sim)).as_matrix(), sim.as_matrix(), atol=1e-13
    )


def _vee(m, scale):
    linear = m[:3, :3]
    omega = 0.5 * np.array(
        [linear[2, 1] - linear[1, 2], linear[0, 2] - linear[2, 0], linear[1, 0] - linear[0, 1]]
    )
    return np.concatenate([m[:3, 3], omega] + ([[np.trace(linear) / 3.0]] if scale else []))


def test_left_right_perturbations():
    r"""$\mathrm{Exp}(\xi_L) X = X \mathrm{Exp}(\xi_R)$; the converted Jacobian of $X \cdot Y$ with
    respect to $X$ predicts left perturbations to first order (finite differences on matrices)."""
    step = 1e-6

    def evaluate(group, tangents, xi_right):
        x, y = group.exp(tangents), group.exp(tangents[::-1] * 0.5)
        xi_left = cv.left_from_right_tangent(x, xi_right)
        jac_right = jax.vmap(lieax.jacobian(lambda a, b: a @ b))(x, y)
        jac_left = cv.left_from_right_jacobian(jac_right, at=x, value=x @ y)
        dim = tangents.shape[-1]
        shifts = jnp.concatenate([jnp.eye(dim), -jnp.eye(dim)]) * step
        return {
            "left_moved": (group.exp(xi_left) @ x).as_matrix(),
            "right_moved": x.rplus(xi_right).as_matrix(),
            "back": cv.right_from_left_tangent(x, xi_left),
            "jac_right": jac_right,
            "jac_left": jac_left,
            "jac_back": cv.right_from_left_jacobian(jac_left, at=x, value=x @ y),
            "base": (x @ y).as_matrix(),
            "moved": jax.vmap(lambda d: (group.exp(d[None]) @ x @ y).as_matrix())(shifts),
        }

    for group, tangents in ((SE3, SE3_TANGENTS), (Sim3, SIM3_TANGENTS)):
        xi_right = RNG.normal(size=tangents.shape) * 0.3
        out = jax.tree_util.tree_map(
            np.asarray,
            jax.jit(evaluate, static_argnums=0)(
                group, jnp.asarray(tangents), jnp.asarray(xi_right)
            ),
        )
        np.testing.assert_allclose(out["left_moved"], out["right_moved"], atol=1e-12)
        np.testing.assert_allclose(out["back"], xi_right, atol=1e-12)
        np.testing.assert_allclose(out["jac_back"], out["jac_right"], atol=1e-12)
        dim = tangents.shape[1]
        for i in range(len(tangents)):  # left perturbations Exp(±εe_k) X Y, by matrix logarithms
            logs = [
                scipy.linalg.logm(m[i] @ np.linalg.inv(out["base"][i])).real for m in out["moved"]
            ]
            columns = [(logs[k] - logs[k + dim]) / (2 * step) for k in range(dim)]
            expected = np.stack([_vee(c, group is Sim3) for c in columns], axis=1)
            np.testing.assert_allclose(out["jac_left"][i], expected, atol=1e-6)


def test_ceres_quaternion():
    """Ceres' plus is Exp(2δ) on the left, i.e. lieax's right tangent 2Rᵀδ (exactly, not only to
    first order); minus inverts plus; PlusJacobian is the raw derivative at 0; the Jacobian
    converters match finite differences through Ceres' plus."""

    @jax.jit
    def evaluate(omega, delta, p):
        q = SO3.exp(omega)
        plus = cv.ceres_quaternion_plus(q.wxyz, delta)
        jac = jax.vmap(lieax.jacobian(lambda r, point: r @ point))(q, p)
        converted = cv.jacobian_to_ceres_delta(jac, q)
        through_plus = jax.vmap(
            jax.jacfwd(lambda w, d, point: SO3(cv.ceres_quaternion_plus(w, d)) @ point, argnums=1)
        )(q.wxyz, jnp.zeros_like(delta), p)
        return {
            "plus": plus,
            "left": (SO3.exp(2.0 * delta) @ q).wxyz,
            "right": q.rplus(cv.tangent_from_ceres_delta(q, delta)).wxyz,
            "delta_back": cv.tangent_to_ceres_delta(q, cv.tangent_from_ceres_delta(q, delta)),
            "minus": cv.ceres_quaternion_minus(plus, q.wxyz),
            "q": q.wxyz,
            "plus_zero": cv.ceres_quaternion_plus(q.wxyz, jnp.zeros(3)),
            "minus_self": cv.ceres_quaternion_minus(q.wxyz, q.wxyz),
            "plus_jacobian": cv.ceres_quaternion_plus_jacobian(q.wxyz),
            "raw": jax.vmap(jax.jacfwd(cv.ceres_quaternion_plus, argnums=1))(
                q.wxyz, jnp.zeros_like(delta)
            ),
            "jac": jac,
            "converted": converted,
            "through_plus": through_plus,
            "back": cv.jacobian_from_ceres_delta(converted, q),
        }

    delta = RNG.normal(size=(4, 3)) * 0.4
    out = evaluate(jnp.asarray(SE3_TANGENTS[:, 3:]), jnp.asarray(delta), jnp.asarray(POINTS))
    np.testing.assert_allclose(out["plus"], out["left"], atol=1e-15)
    np.testing.assert_allclose(out["plus"], out["right"], atol=1e-14)
    np.testing.assert_allclose(out["delta_back"], delta, atol=1e-15)
    np.testing.assert_allclose(out["minus"], delta, atol=1e-14)
    np.testing.assert_allclose(out["plus_zero"], out["q"], atol=0)
    np.testing.assert_allclose(out["minus_self"], 0.0, atol=1e-15)
    np.testing.assert_allclose(out["plus_jacobian"], out["raw"], atol=1e-15)
    # d(R p)/dδ through Ceres' plus = lieax's d(R p)/dω converted
    np.testing.assert_allclose(out["converted"], out["through_plus"], atol=1e-14)
    np.testing.assert_allclose(out["back"], out["jac"], atol=1e-14)


def test_s2_tangent_conversion():
    r"""Both bases span the tangent plane: $B_g \xi_g = B_l \xi_l$; GTSAM's basis is orthonormal and
    tangent."""
    p = jnp.asarray(DIRECTIONS)
    basis_g = cv.s2_gtsam_basis(p)
    np.testing.assert_allclose(
        np.swapaxes(basis_g, -1, -2) @ basis_g, np.broadcast_to(np.eye(2), (4, 2, 2)), atol=1e-15
    )
    np.testing.assert_allclose(np.einsum("nij,ni->nj", basis_g, DIRECTIONS), 0.0, atol=1e-15)
    xi = jnp.asarray(RNG.normal(size=(4, 2)))
    xi_g = cv.s2_tangent_to_gtsam(S2(p), xi)
    np.testing.assert_allclose(
        np.einsum("nij,nj->ni", basis_g, xi_g),
        np.einsum("nij,nj->ni", S2(p).basis(), xi),
        atol=1e-15,
    )
    np.testing.assert_allclose(cv.s2_tangent_from_gtsam(p, xi_g), xi, atol=1e-15)


# ---- against GTSAM --------------------------------------------------------------------------------


def _h(rows, cols):
    return np.zeros((rows, cols), order="F")


def test_se3_against_gtsam():
    gtsam = pytest.importorskip("gtsam")

    @jax.jit
    def evaluate(xis, etas, points):
        x, y = SE3.exp(xis), SE3.exp(etas)
        compose = jax.vmap(lieax.jacobian(lambda a, b: a @ b, (0, 1)))(x, y)
        between = jax.vmap(lieax.jacobian(lambda a, b: a.between(b), (0, 1)))(x, y)
        act = jax.vmap(lieax.jacobian(lambda a, p: a @ p, (0, 1)))(x, points)
        return {
            "matrix": x.as_matrix(),
            "log": x.log(),
            "adjoint": x.adjoint(),
            "jr": SE3.right_jacobian(xis),
            "jr_inverse": SE3.right_jacobian_inverse(xis),
            "compose": compose,
            "between": between,
            "act": act,
            "log_jacobian": jax.vmap(lieax.jacobian(lambda a: a.log()))(x),
            "local": cv.gtsam_local_coordinates(x, y),
            "moved": x @ points,
        }

    etas = SE3_TANGENTS[::-1] * 0.7
    out = jax.tree_util.tree_map(
        np.asarray, evaluate(jnp.asarray(SE3_TANGENTS), jnp.asarray(etas), jnp.asarray(POINTS))
    )
    to_g = lambda m, **kw: np.asarray(cv.se3_jacobian_to_gtsam(jnp.asarray(m), **kw))
    for i, (xi, eta, point) in enumerate(zip(SE3_TANGENTS, etas, POINTS)):
        xi_g, eta_g = (np.asarray(cv.se3_tangent_to_gtsam(jnp.asarray(v))) for v in (xi, eta))
        x, y = gtsam.Pose3.Expmap(xi_g), gtsam.Pose3.Expmap(eta_g)
        np.testing.assert_allclose(out["matrix"][i], x.matrix(), atol=1e-12)
        np.testing.assert_allclose(
            cv.se3_tangent_to_gtsam(out["log"][i]), gtsam.Pose3.Logmap(x), atol=1e-9
        )
        np.testing.assert_allclose(to_g(out["adjoint"][i]), x.AdjointMap(), atol=1e-12)
        np.testing.assert_allclose(
            to_g(out["jr"][i]), gtsam.Pose3.ExpmapDerivative(xi_g), atol=1e-9
        )
        np.testing.assert_allclose(
            to_g(out["jr_inverse"][i]), gtsam.Pose3.LogmapDerivative(xi_g), atol=1e-6
        )
        h_log = _h(6, 6)
        gtsam.Pose3.Logmap(x, h_log)
        np.testing.assert_allclose(to_g(out["log_jacobian"][i]), h_log, atol=1e-6)
        h1, h2 = _h(6, 6), _h(6, 6)
        x.compose(y, h1, h2)
        np.testing.assert_allclose(to_g(out["compose"][0][i]), h1, atol=1e-12)
        np.testing.assert_allclose(to_g(out["compose"][1][i]), h2, atol=1e-12)
        h1, h2 = _h(6, 6), _h(6, 6)
        x.between(y, h1, h2)
        np.testing.assert_allclose(to_g(out["between"][0][i]), h1, atol=1e-12)
        np.testing.assert_allclose(to_g(out["between"][1][i]), h2, atol=1e-12)
        h_self, h_point = _h(3, 6), _h(3, 3)
        moved = x.transformFrom(point, h_self, h_point)
        np.testing.assert_allclose(out["moved"][i], moved, atol=1e-12)
        np.testing.assert_allclose(to_g(out["act"][0][i], rows=False), h_self, atol=1e-12)
        np.testing.assert_allclose(out["act"][1][i], h_point, atol=1e-12)
        np.testing.assert_allclose(
            cv.se3_tangent_to_gtsam(out["local"][i]), x.localCoordinates(y), atol=1e-9
        )


def test_sim3_against_gtsam():
    """GTSAM's Similarity3 (matrix [R, t_g; 0, 1/s]) against lieax's Sim3 through the converters:
    Expmap, Logmap, AdjointMap, transformFrom and its Jacobians, compose."""
    gtsam = pytest.importorskip("gtsam")

    @jax.jit
    def evaluate(xis, etas, points):
        x, y = Sim3.exp(xis), Sim3.exp(etas)
        act = jax.vmap(lieax.jacobian(lambda a, p: a @ p, (0, 1)))(x, points)
        return {
            "x": x,
            "composed": x @ y,
            "log": x.log(),
            "adjoint": x.adjoint(),
            "moved": x @ points,
            "act": act,
            "matrix": x.as_matrix(),
        }

    etas = SIM3_TANGENTS[::-1] * 0.7
    out = evaluate(jnp.asarray(SIM3_TANGENTS), jnp.asarray(etas), jnp.asarray(POINTS))
    for i, (xi, eta, point) in enumerate(zip(SIM3_TANGENTS, etas, POINTS)):
        x = gtsam.Similarity3.Expmap(np.asarray(cv.sim3_tangent_to_gtsam(jnp.asarray(xi))))
        y = gtsam.Similarity3.Expmap(np.asarray(cv.sim3_tangent_to_gtsam(jnp.asarray(eta))))
        rotation, translation, scale = (np.asarray(v) for v in cv.sim3_to_gtsam(out["x"][i]))
        np.testing.assert_allclose(rotation, x.rotation().matrix(), atol=1e-12)
        np.testing.assert_allclose(translation, x.translation(), atol=1e-12)
        np.testing.assert_allclose(scale, x.scale(), rtol=1e-13)
        from_gtsam = cv.sim3_from_gtsam(x.rotation().matrix(), x.translation(), x.scale())
        np.testing.assert_allclose(from_gtsam.as_matrix(), out["matrix"][i], atol=1e-12)
        composed = x.compose(y)
        expected = cv.sim3_from_gtsam(
            composed.rotation().matrix(), composed.translation(), composed.scale()
        )
        np.testing.assert_allclose(out["composed"][i].as_matrix(), expected.as_matrix(), atol=1e-11)
        np.testing.assert_allclose(
            cv.sim3_tangent_to_gtsam(out["log"][i]), gtsam.Similarity3.Logmap(x), atol=1e-9
        )
        np.testing.assert_allclose(
            cv.sim3_jacobian_to_gtsam(out["adjoint"][i]), x.AdjointMap(), atol=1e-12
        )
        h1, h2 = _h(3, 7), _h(3, 3)
        moved = x.transformFrom(point, h1, h2)
        np.testing.assert_allclose(out["moved"][i], moved, atol=1e-12)
        np.testing.assert_allclose(
            cv.sim3_jacobian_to_gtsam(out["act"][0][i], rows=False), h1, atol=1e-12
        )
        np.testing.assert_allclose(out["act"][1][i], h2, atol=1e-12)


def test_s2_against_gtsam():
    """GTSAM's Unit3: basis; errorVector's H_q (any basis change works: H_q = B_pᵀ B_q); rotate's
    HR and Hp against lieax.jacobian of `S2.rotate` converted to GTSAM's bases; retract agrees
    with lieax's retraction to third order."""
    gtsam = pytest.importorskip("gtsam")
    p = S2(jnp.asarray(DIRECTIONS))
    q = S2(jnp.asarray(DIRECTIONS[::-1] + 0.3 * DIRECTIONS))
    q = q.normalize()
    rotations = SO3.exp(jnp.asarray(SE3_TANGENTS[:, 3:]))
    basis_g = np.asarray(cv.s2_gtsam_basis(p.unit_vector()))
    small = 1e-3 * RNG.normal(size=(4, 2))
    for i in range(4):
        unit_p = gtsam.Unit3(np.asarray(p.unit_vector()[i]))
        unit_q = gtsam.Unit3(np.asarray(q.unit_vector()[i]))
        np.testing.assert_allclose(basis_g[i], unit_p.basis(), atol=1e-15)
        h_p, h_q = _h(2, 2), _h(2, 2)
        error = unit_p.errorVector(unit_q, h_p, h_q)
        np.testing.assert_allclose(error, unit_p.basis().T @ unit_q.point3(), atol=1e-15)
        np.testing.assert_allclose(h_q, unit_p.basis().T @ unit_q.basis(), atol=1e-15)
        retracted = unit_p.retract(small[i]).point3()
        ours = p[i].rplus(cv.s2_tangent_from_gtsam(p[i], jnp.asarray(small[i]))).unit_vector()
        np.testing.assert_allclose(ours, retracted, atol=1e-8)  # |ξ|³/3 ≈ 1e-9
    if not MANIFOLD_PATCH:
        pytest.skip("lieax.jacobian of S2 needs AbstractManifold in _base.py")
    jac_r, jac_p = jax.jit(jax.vmap(lieax.jacobian(lambda r, d: d.rotate(r), (0, 1))))(rotations, p)
    moved = p.rotate(rotations)
    for i in range(4):
        rotation = gtsam.Rot3(np.asarray(rotations.as_matrix()[i]))
        h_r, h_d = _h(2, 3), _h(2, 2)
        rotation.rotate(gtsam.Unit3(np.asarray(p.unit_vector()[i])), h_r, h_d)
        np.testing.assert_allclose(
            cv.s2_jacobian_to_gtsam(jac_r[i], row_direction=moved[i]), h_r, atol=1e-12
        )
        np.testing.assert_allclose(
            cv.s2_jacobian_to_gtsam(jac_p[i], row_direction=moved[i], col_direction=p[i]),
            h_d,
            atol=1e-12,
        )
