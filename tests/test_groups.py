"""Values and algebraic identities of every registered group; shapes, dtypes, pytrees.

Everything is computed on batches that hold the regimes of `registry.py` (identity, 1e-9 from it,
pure translations, ~1e-4 rad, π - 1e-6, random) plus random elements, against NumPy matrix
formulas (`scipy.linalg.expm` / `logm` of `hat`). Each group's quantities are evaluated by a few
jitted calls cached per group; the tests compare them.
"""

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from _stacked import stacked, unstacked
from registry import (
    GROUPS,
    SE2,
    SE3,
    SO2,
    SO3,
    VALUE_ATOL_F64,
    Sim3,
    random_points,
    random_tangents,
    regime_tangents,
)
from scipy.spatial.transform import Rotation

import lieax

RANDOM_COUNT = 24


def assert_close(actual, expected, what, atol=VALUE_ATOL_F64):
    actual, expected = np.asarray(actual), np.asarray(expected)
    assert actual.shape == expected.shape, f"{what}: shape {actual.shape} != {expected.shape}"
    scale = max(1.0, float(np.max(np.abs(expected), initial=0.0)))
    error = float(np.max(np.abs(actual - expected), initial=0.0))
    assert error <= atol * scale, f"{what}: max error {error:.3g} > {atol * scale:.3g}"


def sample_tangents(spec):
    """Tangents of every regime followed by random ones (angles up to 3 rad)."""
    return np.concatenate([regime_tangents(spec), random_tangents(spec, RANDOM_COUNT, seed=7)])


def as_matrices(x):
    return np.asarray(x.as_matrix())


# ---- one jitted evaluation of the group's identities per group -----------------------------------


@functools.cache
def identities(group_name):
    """Both sides of the identities the tests check, for a batch X (all regimes + random), Y and
    Z random, points p, tangents ξ (the regimes)."""
    spec = next(s for s in GROUPS if s.name == group_name)
    G = spec.cls
    xis = sample_tangents(spec)
    count = len(xis)
    etas = random_tangents(spec, count, seed=8)
    zetas = random_tangents(spec, count, seed=9)
    points = random_points(spec, count, seed=10)

    rescale = np.ones(G.parameters_dim)
    rescale[: spec.rotation_parameters] = 1.7  # drifted rotation parameters

    def evaluate(xis, etas, zetas, points):
        # Calls of the same operation share one batched call (a leading axis of cases) where
        # their inputs allow it: the values are the same, the program (and its compilation) is
        # about a third smaller than with a copy of the kernel per call.
        x, y, z = unstacked(G.exp(jnp.stack([xis, etas, zetas])), 3)
        identity = G.identity((count,))
        x_inv = x.inverse()
        ad = lambda element: element.adjoint()
        log_x, identity_log = stacked(x, identity).log()
        rminus, rminus_self = stacked(x, x).rminus(stacked(y, x))
        exp_log_x, exp_ad = unstacked(
            G.exp(jnp.stack([log_x, jnp.einsum("...ij,...j->...i", ad(x), etas)])), 2
        )
        rplus, rplus_rminus = unstacked(y.rplus(jnp.stack([xis, rminus])), 2)
        # interpolate(X, Y, t) at t = 0, 1, 1/2 and interpolate(Y, X, 1/2)
        t = jnp.asarray([0.0, 1.0, 0.5, 0.5])[:, None]
        interpolated = unstacked(stacked(x, x, x, y).interpolate(stacked(y, y, y, x), t), 4)
        jr, jr_minus = G.right_jacobian(jnp.stack([xis, -xis]))
        return {
            "x": x.as_matrix(),
            "y": y.as_matrix(),
            "z": z.as_matrix(),
            "x_params": x.parameters(),
            "hat": G.hat(xis),
            "vee_hat": G.vee(G.hat(xis)),
            "log_x": log_x,
            "exp_log_x": exp_log_x.as_matrix(),
            "identity": identity.as_matrix(),
            "identity_log": identity_log,
            "identity_x": (identity @ x).as_matrix(),
            "x_identity": (x @ identity).as_matrix(),
            "x_x_inv": (x @ x_inv).as_matrix(),
            "x_inv_x": (x_inv @ x).as_matrix(),
            "x_inv": x_inv.as_matrix(),
            "inverse_inverse": x_inv.inverse().as_matrix(),
            "xy_z": ((x @ y) @ z).as_matrix(),
            "x_yz": (x @ (y @ z)).as_matrix(),
            "xy": (x @ y).as_matrix(),
            "ad_xy": ad(x @ y),
            "ad_x_ad_y": ad(x) @ ad(y),
            "ad_x": ad(x),
            "ad_x_inv": ad(x_inv),
            "conjugated_exp": (x @ y @ x_inv).as_matrix(),  # X Exp(η) X⁻¹, Y = Exp(η)
            "exp_ad": exp_ad.as_matrix(),
            "act": x @ points,
            "act_composed": (x @ y) @ points,
            "act_nested": x @ (y @ points),
            "act_inverse": x_inv @ (x @ points),
            "between": x.between(y).as_matrix(),
            "rplus": rplus.as_matrix(),
            "rminus": rminus,
            "rplus_rminus": rplus_rminus.as_matrix(),
            "rminus_self": rminus_self,
            "interpolate_0": interpolated[0].as_matrix(),
            "interpolate_1": interpolated[1].as_matrix(),
            "interpolate_half": interpolated[2].as_matrix(),
            "interpolate_half_reversed": interpolated[3].as_matrix(),
            "from_matrix": G.from_matrix(x.as_matrix()).as_matrix(),
            "normalized": G(x.parameters() * rescale).normalize().as_matrix(),
            "normalize_idempotent": x.normalize().parameters(),
            "jr": jr,
            "jr_inverse": G.right_jacobian_inverse(xis),
            "jl": G.left_jacobian(xis),
            "jl_inverse": G.left_jacobian_inverse(xis),
            "jr_minus": jr_minus,
            "ad_exp": ad(x),  # Ad(Exp ξ), X = Exp(ξ)
        }

    out = jax.jit(evaluate)(xis, etas, zetas, points)
    out = {key: np.asarray(value) for key, value in out.items()}
    return out, {"xis": xis, "etas": etas, "zetas": zetas, "points": points}


def _w_by_quadrature(sigma, omega):
    """`W = ∫₀¹ e^(στ) R(τω) dτ` by 40-point Gauss-Legendre quadrature (SciPy's rotation vectors):
    the translation block of Sim3's Exp, computed without `expm` or `logm`."""
    nodes, weights = np.polynomial.legendre.leggauss(40)
    tau, weights = 0.5 * (nodes + 1.0), 0.5 * weights
    rotations = Rotation.from_rotvec(tau[:, None] * omega).as_matrix()
    return np.einsum("k,kij->ij", weights * np.exp(sigma * tau), rotations)


def test_reference_matrix_functions(spec):
    """The NumPy references the tests rely on: `logm(expm(ξ)) = ξ` on every regime and random
    tangent (angles below π), and for a group with a scale, `expm` against the closed form
    `[e^σ R(ω), W v; 0, 1]` with `W` by quadrature."""
    _, inputs = identities(spec.name)
    for xi in inputs["xis"]:
        matrix = spec.expm(xi)
        np.testing.assert_allclose(spec.logm(matrix), xi, rtol=0, atol=1e-12)
        if spec.has_scale:
            v, omega, sigma = xi[:3], xi[3:6], xi[6]
            expected = np.eye(4)
            expected[:3, :3] = np.exp(sigma) * Rotation.from_rotvec(omega).as_matrix()
            expected[:3, 3] = _w_by_quadrature(sigma, omega) @ v
            np.testing.assert_allclose(matrix, expected, rtol=0, atol=1e-13 * np.abs(matrix).max())


def test_hat_and_vee(spec):
    out, inputs = identities(spec.name)
    expected = np.stack([spec.hat(xi) for xi in inputs["xis"]])
    assert_close(out["hat"], expected, f"{spec}.hat")
    assert_close(out["vee_hat"], inputs["xis"], f"{spec}.vee(hat(ξ))")


def test_exp_matches_expm_of_hat(spec):
    out, inputs = identities(spec.name)
    expected = np.stack([spec.expm(xi) for xi in inputs["xis"]])
    assert_close(out["x"], expected, f"{spec}.exp")


def test_log_matches_logm(spec):
    out, inputs = identities(spec.name)
    expected = np.stack([spec.logm(m) for m in out["x"]])
    assert_close(out["log_x"], expected, f"{spec}.log")
    # every test angle is below π, so Log inverts Exp
    assert_close(out["log_x"], inputs["xis"], f"{spec}.log(exp(ξ))")


def test_exp_of_log(spec):
    out, _ = identities(spec.name)
    assert_close(out["exp_log_x"], out["x"], f"{spec}: exp(log X)")


def test_identity_element(spec):
    out, _ = identities(spec.name)
    eye = np.broadcast_to(np.eye(spec.n), out["x"].shape)
    assert_close(out["identity"], eye, f"{spec}.identity")
    assert_close(out["identity_log"], np.zeros_like(out["log_x"]), f"{spec}: log(identity)")
    assert_close(out["identity_x"], out["x"], f"{spec}: I X")
    assert_close(out["x_identity"], out["x"], f"{spec}: X I")


def test_inverse(spec):
    out, _ = identities(spec.name)
    eye = np.broadcast_to(np.eye(spec.n), out["x"].shape)
    assert_close(out["x_x_inv"], eye, f"{spec}: X X⁻¹")
    assert_close(out["x_inv_x"], eye, f"{spec}: X⁻¹ X")
    assert_close(out["x_inv"], np.linalg.inv(out["x"]), f"{spec}.inverse")
    assert_close(out["inverse_inverse"], out["x"], f"{spec}: (X⁻¹)⁻¹")


def test_compose_is_matrix_product_and_associative(spec):
    out, _ = identities(spec.name)
    assert_close(out["xy"], out["x"] @ out["y"], f"{spec}: X Y")
    assert_close(out["xy_z"], out["x_yz"], f"{spec}: (X Y) Z")


def test_adjoint(spec):
    out, _ = identities(spec.name)
    expected = np.stack([spec.adjoint(m) for m in out["x"]])
    assert_close(out["ad_x"], expected, f"{spec}.adjoint vs X hat(e_k) X⁻¹")
    assert_close(out["ad_xy"], out["ad_x_ad_y"], f"{spec}: Ad(XY) = Ad(X) Ad(Y)")
    assert_close(out["ad_x_inv"], np.linalg.inv(out["ad_x"]), f"{spec}: Ad(X⁻¹) = Ad(X)⁻¹")
    assert_close(out["conjugated_exp"], out["exp_ad"], f"{spec}: X Exp(ξ) X⁻¹ = Exp(Ad ξ)")


def test_act(spec):
    out, inputs = identities(spec.name)
    expected = np.stack([spec.act(m, p) for m, p in zip(out["x"], inputs["points"])])
    assert_close(out["act"], expected, f"{spec}: X @ p")
    assert_close(out["act_composed"], out["act_nested"], f"{spec}: (X Y) p = X (Y p)")
    assert_close(out["act_inverse"], inputs["points"], f"{spec}: X⁻¹ (X p)")


def test_between_rplus_rminus(spec):
    out, inputs = identities(spec.name)
    x, y = out["x"], out["y"]
    assert_close(out["between"], np.linalg.inv(x) @ y, f"{spec}.between")
    expected_rplus = y @ np.stack([spec.expm(xi) for xi in inputs["xis"]])
    assert_close(out["rplus"], expected_rplus, f"{spec}.rplus")
    expected_rminus = np.stack([spec.logm(np.linalg.inv(b) @ a) for a, b in zip(x, y)])
    assert_close(out["rminus"], expected_rminus, f"{spec}.rminus = Log(Y⁻¹ X)")
    assert_close(out["rplus_rminus"], x, f"{spec}: Y ⊕ (X ⊖ Y) = X")
    assert_close(out["rminus_self"], np.zeros_like(out["rminus"]), f"{spec}: X ⊖ X")


def test_interpolate(spec):
    out, _ = identities(spec.name)
    x, y = out["x"], out["y"]
    assert_close(out["interpolate_0"], x, f"{spec}.interpolate(t=0)")
    assert_close(out["interpolate_1"], y, f"{spec}.interpolate(t=1)", atol=1e-9)
    expected = np.stack(
        [a @ spec.expm(0.5 * spec.logm(np.linalg.inv(a) @ b)) for a, b in zip(x, y)]
    )
    assert_close(out["interpolate_half"], expected, f"{spec}.interpolate(t=0.5)")
    assert_close(out["interpolate_half"], out["interpolate_half_reversed"], f"{spec} midpoint")


def test_from_matrix_and_normalize(spec):
    out, _ = identities(spec.name)
    assert_close(out["from_matrix"], out["x"], f"{spec}.from_matrix(as_matrix(X))")
    assert_close(out["normalized"], out["x"], f"{spec}.normalize() of scaled parameters")
    assert_close(out["normalize_idempotent"], out["x_params"], f"{spec}.normalize() of X")


def test_tangent_map_identities(spec):
    """`Jl = Ad(Exp ξ) Jr`, `Jl(ξ) = Jr(-ξ)`, `Jr Jr⁻¹ = I`, `Jl Jl⁻¹ = I`."""
    out, _ = identities(spec.name)
    eye = np.broadcast_to(np.eye(spec.dim), out["jr"].shape)
    assert_close(out["jl"], out["ad_exp"] @ out["jr"], f"{spec}: Jl = Ad Jr")
    assert_close(out["jl"], out["jr_minus"], f"{spec}: Jl(ξ) = Jr(-ξ)")
    assert_close(out["jr"] @ out["jr_inverse"], eye, f"{spec}: Jr Jr⁻¹", atol=1e-9)
    assert_close(out["jr_inverse"] @ out["jr"], eye, f"{spec}: Jr⁻¹ Jr", atol=1e-9)
    assert_close(out["jl"] @ out["jl_inverse"], eye, f"{spec}: Jl Jl⁻¹", atol=1e-9)


def test_from_matrix_projects_onto_the_group(spec):
    """A perturbed (non-orthogonal) matrix maps to a valid element close to it."""
    out, _ = identities(spec.name)
    rng = np.random.default_rng(3)
    noisy = out["x"].copy()
    k = spec.space
    noisy[..., :k, :k] += 1e-3 * rng.normal(size=noisy[..., :k, :k].shape)
    projected = np.asarray(spec.cls.from_matrix(jnp.asarray(noisy)).as_matrix())
    rotation = spec.rotation_block(projected)
    assert_close(
        rotation @ np.swapaxes(rotation, -1, -2),
        np.broadcast_to(np.eye(k), rotation.shape),
        f"{spec}.from_matrix orthogonality",
    )
    assert np.allclose(np.linalg.det(rotation), 1.0)
    assert np.max(np.abs(projected - out["x"])) < 1e-2


@pytest.mark.parametrize("G", [SO3, SE3, Sim3], ids=lambda G: G.__name__)
def test_quaternion_sign_does_not_matter(G):
    """`q` and `-q` are the same rotation: same matrix, Log, action, adjoint and Jacobians
    (random rotations of any angle up to π, from both hemispheres)."""
    spec = next(s for s in GROUPS if s.cls is G)
    x = G.sample_uniform(jax.random.key(3), (32,))
    flip = jnp.where(jnp.arange(G.parameters_dim) < 4, -1.0, 1.0)
    negated = G(x.parameters() * flip)
    points = jnp.asarray(random_points(spec, 32, seed=15))
    y = G.exp(jnp.asarray(random_tangents(spec, 32, seed=16)))

    @jax.jit
    def evaluate(x):
        return (
            x.as_matrix(),
            x.log(),
            x @ points,
            x.adjoint(),
            (x @ y).as_matrix(),
            y.rminus(x),
            jax.vmap(lieax.jacobian(lambda a, p: (a.log(), a @ p, y[0].rminus(a)), (0, 1)))(
                x, points
            ),
        )

    for a, b in zip(
        jax.tree_util.tree_leaves(evaluate(x)), jax.tree_util.tree_leaves(evaluate(negated))
    ):
        np.testing.assert_allclose(a, b, rtol=0, atol=1e-12)


# ---- construction, shapes, dtypes, pytrees -------------------------------------------------------


@pytest.mark.parametrize("batch_shape", [(), (3,), (2, 5)], ids=str)
def test_shapes(spec, batch_shape):
    G = spec.cls
    d, n, s = G.tangent_dim, G.matrix_dim, G.space_dim

    def shapes():
        identity = G.identity(batch_shape)
        sample = G.sample_uniform(jax.random.key(0), batch_shape)
        tangent = jnp.zeros((*batch_shape, d))
        return {
            "identity": identity.parameters(),
            "identity_matrix": identity.as_matrix(),
            "sample": sample.parameters(),
            "log": sample.log(),
            "adjoint": sample.adjoint(),
            "act": sample @ jnp.zeros((*batch_shape, s)),
            "act_single_point": sample @ jnp.zeros(s),
            "rminus": sample.rminus(identity),
            "hat": G.hat(tangent),
            "vee": G.vee(G.hat(tangent)),
            "jr": G.right_jacobian(tangent),
            "jl_inverse": G.left_jacobian_inverse(tangent),
        }

    out = jax.eval_shape(shapes)
    expected = {
        "identity": (G.parameters_dim,),
        "identity_matrix": (n, n),
        "sample": (G.parameters_dim,),
        "log": (d,),
        "adjoint": (d, d),
        "act": (s,),
        "act_single_point": (s,),
        "rminus": (d,),
        "hat": (n, n),
        "vee": (d,),
        "jr": (d, d),
        "jl_inverse": (d, d),
    }
    for key, shape in expected.items():
        assert out[key].shape == (*batch_shape, *shape), key
    assert G.identity(batch_shape).batch_shape == batch_shape


def test_sample_uniform_is_valid_and_deterministic(spec):
    G = spec.cls
    first = G.sample_uniform(jax.random.key(1), (200,))
    again = G.sample_uniform(jax.random.key(1), (200,))
    other = G.sample_uniform(jax.random.key(2), (200,))
    np.testing.assert_array_equal(first.parameters(), again.parameters())
    assert not np.allclose(first.parameters(), other.parameters())
    matrices = as_matrices(first)
    k = spec.space
    rotation = spec.rotation_block(matrices)
    np.testing.assert_allclose(
        rotation @ np.swapaxes(rotation, 1, 2),
        np.broadcast_to(np.eye(k), rotation.shape),
        atol=1e-12,
    )
    np.testing.assert_allclose(np.linalg.det(rotation), 1.0, atol=1e-12)
    if spec.has_translation:
        assert np.all(np.abs(matrices[:, :k, k]) <= 1.0)
    if spec.has_scale:  # log-scales uniform in [-1, 1]
        log_scales = np.log(np.linalg.det(matrices[:, :k, :k])) / k
        assert np.all(np.abs(log_scales) <= 1.0) and np.std(log_scales) > 0.4
    # uniform rotations: the mean of the rotation matrices is near zero
    assert np.max(np.abs(rotation.mean(axis=0))) < 0.25


@pytest.mark.parametrize("dtype", [jnp.float32, jnp.float64], ids=["float32", "float64"])
def test_dtype_is_preserved(spec, dtype):
    G = spec.cls

    def outputs():
        x = G.sample_uniform(jax.random.key(0), (4,), dtype=dtype)
        y = G.exp(jnp.ones((4, spec.dim), dtype=dtype))
        points = jnp.ones((4, spec.space), dtype=dtype)
        return [
            G.identity((2,), dtype=dtype).parameters(),
            x.parameters(),
            x.log(),
            (x @ y).parameters(),
            x.inverse().parameters(),
            x @ points,
            x.between(y).parameters(),
            x.adjoint(),
            x.as_matrix(),
            x.rplus(y.log()).parameters(),
            x.rminus(y),
            x.interpolate(y, jnp.asarray(0.3, dtype)).parameters(),
            G.right_jacobian(x.log()),
            G.right_jacobian_inverse(x.log()),
            G.from_matrix(x.as_matrix()).parameters(),
            x.normalize().parameters(),
            lieax.jacobian(lambda a, b: a @ b, (0, 1))(x, y)[0],
            lieax.jacobian(lambda a, p: a @ p, (0, 1), mode="rev")(x, points)[1],
        ]

    for i, value in enumerate(jax.eval_shape(outputs)):
        assert value.dtype == dtype, f"output {i}: {value.dtype}"


def test_pytree_jit_and_indexing(spec):
    G = spec.cls
    x = G.exp(jnp.asarray(random_tangents(spec, 5, seed=11)))
    leaves, treedef = jax.tree_util.tree_flatten(x)
    assert len(leaves) == 1 and leaves[0].shape == (5, G.parameters_dim)
    rebuilt = jax.tree_util.tree_unflatten(treedef, leaves)
    assert type(rebuilt) is G
    np.testing.assert_array_equal(rebuilt.parameters(), x.parameters())
    composed = jax.jit(lambda a, b: a @ b.inverse())(x, x)
    assert type(composed) is G
    np.testing.assert_allclose(
        composed.as_matrix(), np.broadcast_to(np.eye(spec.n), (5, spec.n, spec.n)), atol=1e-12
    )
    np.testing.assert_array_equal(x[2].parameters(), x.parameters()[2])
    assert x[1:3].batch_shape == (2,)
    assert G.__name__ in repr(x)
    with pytest.raises(AttributeError):
        x._params = None


def test_broadcasting(spec):
    G = spec.cls
    x = G.exp(jnp.asarray(random_tangents(spec, 3, seed=12)))[:, None]  # batch (3, 1)
    y = G.exp(jnp.asarray(random_tangents(spec, 4, seed=13)))  # batch (4,)
    cloud = jnp.asarray(random_points(spec, 7, seed=14))
    clouds = jnp.broadcast_to(cloud[:, None, :], (7, 4, spec.space))

    @jax.jit
    def evaluate(x, y, cloud, clouds):
        return {
            "xy": (x @ y).as_matrix(),
            "rminus": x.rminus(y),
            "between": x.between(y).parameters(),
            "interpolate": x.interpolate(y, 0.5).parameters(),
            "interpolate_t": x.interpolate(y, jnp.linspace(0.0, 1.0, 4)).parameters(),
            "single_on_cloud": y[0] @ cloud,
            "batch_on_clouds": y @ clouds,
            "batch_on_one_cloud_each": y @ cloud[3],
            "rplus_single": y.rplus(jnp.zeros(spec.dim)).parameters(),
        }

    out = evaluate(x, y, cloud, clouds)
    assert out["xy"].shape == (3, 4, spec.n, spec.n)
    np.testing.assert_allclose(out["xy"], as_matrices(x) @ as_matrices(y), atol=1e-12)
    assert out["rminus"].shape == (3, 4, spec.dim)
    for key in ("between", "interpolate", "interpolate_t"):
        assert out[key].shape == (3, 4, spec.cls.parameters_dim), key
    expected = np.stack([spec.act(as_matrices(y)[0], p) for p in np.asarray(cloud)])
    np.testing.assert_allclose(out["single_on_cloud"], expected, atol=1e-12)
    assert out["batch_on_clouds"].shape == (7, 4, spec.space)
    np.testing.assert_allclose(
        out["batch_on_clouds"][3], out["batch_on_one_cloud_each"], atol=1e-12
    )
    assert out["rplus_single"].shape == (4, spec.cls.parameters_dim)


# ---- group-specific constructors and conversions -------------------------------------------------


def test_so3_quaternion_conventions():
    rotations = Rotation.random(10, random_state=0)
    xyzw = rotations.as_quat()  # scalar-last
    x = SO3.from_xyzw(jnp.asarray(xyzw))
    np.testing.assert_allclose(x.as_matrix(), rotations.as_matrix(), atol=1e-12)
    np.testing.assert_allclose(x.as_xyzw(), xyzw, atol=1e-15)
    np.testing.assert_allclose(x.parameters(), np.roll(xyzw, 1, axis=-1), atol=1e-15)  # wxyz
    np.testing.assert_allclose(x.log(), rotations.as_rotvec(), atol=1e-12)
    np.testing.assert_allclose(
        SO3.from_rotvec(jnp.asarray(rotations.as_rotvec())).as_matrix(),
        rotations.as_matrix(),
        atol=1e-12,
    )
    # q and -q are the same rotation, with the same Log
    negated = SO3(-x.parameters())
    np.testing.assert_allclose(negated.as_matrix(), x.as_matrix(), atol=1e-12)
    np.testing.assert_allclose(negated.log(), x.log(), atol=1e-12)


def test_so3_rpy_matches_scipy_extrinsic_xyz():
    rng = np.random.default_rng(4)
    rpy = rng.uniform([-np.pi, -1.5, -np.pi], [np.pi, 1.5, np.pi], size=(20, 3))
    x = SO3.from_rpy(*(jnp.asarray(rpy[:, i]) for i in range(3)))
    expected = Rotation.from_euler("xyz", rpy).as_matrix()  # extrinsic x, then y, then z
    np.testing.assert_allclose(x.as_matrix(), expected, atol=1e-12)
    np.testing.assert_allclose(x.as_rpy(), rpy, atol=1e-10)


def test_se_rotation_and_translation():
    for G, R in ((SE2, SO2), (SE3, SO3)):
        dim = G.space_dim
        rotation = R.sample_uniform(jax.random.key(5), (6,))
        translation = jnp.asarray(np.random.default_rng(5).normal(size=(6, dim)))
        x = G.from_rotation_and_translation(rotation, translation)
        assert type(x.rotation()) is R
        np.testing.assert_allclose(x.rotation().as_matrix(), rotation.as_matrix(), atol=1e-15)
        np.testing.assert_allclose(x.translation(), translation, atol=1e-15)
        matrix = np.asarray(x.as_matrix())
        np.testing.assert_allclose(matrix[:, :dim, :dim], rotation.as_matrix(), atol=1e-15)
        np.testing.assert_allclose(matrix[:, :dim, dim], translation, atol=1e-15)
        np.testing.assert_allclose(
            matrix[:, dim], np.eye(dim + 1)[dim].reshape(1, -1).repeat(6, 0), atol=0
        )
        # a single rotation broadcasts against a batch of translations
        y = G.from_rotation_and_translation(rotation[0], translation)
        assert y.batch_shape == (6,)
        # a pure translation moves points by t
        pure = G.from_rotation_and_translation(R.identity(), translation[0])
        np.testing.assert_allclose(pure @ translation, translation + translation[0], atol=1e-15)


def test_sim3_translation_block_by_quadrature():
    """The translation block of `Sim3.exp((v, ω, σ))` is `W v` with `W = ∫₀¹ e^(στ) R(τω) dτ`
    (by quadrature) over a grid of σ in [-30, 12] and θ in [0, 14] that crosses every branch of W's
    coefficients (the joint series, |σ| near 1, θ near 1, large |σ| or θ): the columns of W from
    `v = e_k`."""
    sigmas, thetas = np.meshgrid(
        [0.0, 1e-7, -0.9, 1.0, 3.0, -4.0, -30.0, 12.0], [0.0, 1e-6, 0.99, 1.01, 3.1, 8.0, 14.0]
    )
    axis = np.array([0.3, -0.5, 0.81]) / np.linalg.norm([0.3, -0.5, 0.81])
    cases = [(s, t * axis) for s, t in zip(sigmas.ravel(), thetas.ravel())]
    xis = np.stack(
        [np.concatenate([e, omega, [sigma]]) for sigma, omega in cases for e in np.eye(3)]
    )
    translations = np.asarray(jax.jit(lambda xi: Sim3.exp(xi).translation())(xis))
    for index, (sigma, omega) in enumerate(cases):
        w = translations[3 * index : 3 * index + 3].T
        expected = _w_by_quadrature(sigma, omega)
        np.testing.assert_allclose(
            w,
            expected,
            rtol=0,
            atol=1e-13 * max(1.0, np.abs(expected).max()) + 1e-15 * np.exp(max(sigma, 0.0)),
            err_msg=f"W at σ={sigma}, θ={np.linalg.norm(omega)}",
        )


def test_sim3_constructors_and_broadcasting():
    cloud = np.random.default_rng(0).normal(size=(5, 3))

    @jax.jit
    def evaluate(omega, t, scale, cloud):
        rotation = SO3.exp(omega)
        x = Sim3.from_rotation_translation_scale(rotation, t, scale)
        se3 = SE3.from_rotation_and_translation(rotation, t)
        batch = Sim3.sample_uniform(jax.random.PRNGKey(0), (4, 2))
        return {
            "scale": x.scale(),
            "translation": x.translation(),
            "rotation": x.rotation().as_matrix(),
            "expected_rotation": rotation.as_matrix(),
            "moved": x @ cloud,
            "from_se3": Sim3.from_se3(se3).as_matrix(),
            "se3": se3.as_matrix(),
            "from_scale": Sim3.from_scale(scale) @ t,
            "batch_params": batch.parameters(),
            "composed": (batch @ x).parameters(),
            "scale_jacobian": lieax.jacobian(lambda y: y.scale())(x),
        }

    omega, t = jnp.array([0.1, -0.4, 0.3]), jnp.array([1.0, 2.0, -0.5])
    out = evaluate(omega, t, jnp.array(2.5), jnp.asarray(cloud))
    np.testing.assert_allclose(out["scale"], 2.5, rtol=1e-15)
    np.testing.assert_allclose(out["translation"], t)
    np.testing.assert_allclose(out["rotation"], out["expected_rotation"])
    np.testing.assert_allclose(
        out["moved"], 2.5 * cloud @ np.asarray(out["rotation"]).T + t, atol=1e-14
    )
    np.testing.assert_allclose(out["from_se3"], out["se3"], atol=1e-15)
    np.testing.assert_allclose(out["from_scale"], 2.5 * t, atol=1e-15)
    assert out["batch_params"].shape == (4, 2, 8) and out["composed"].shape == (4, 2, 8)
    np.testing.assert_allclose(out["scale_jacobian"], np.r_[np.zeros(6), 2.5], atol=1e-14)
