"""Bad input fails early (at trace time) with an error that says what was expected."""

import re

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from registry import GROUPS, SE2, SE3, SO2, SO3

import lieax


def raises(exception, *fragments):
    """`pytest.raises` whose message must contain every fragment (matched literally)."""
    return pytest.raises(
        exception, match="(?s)" + "".join(f"(?=.*{re.escape(f)})" for f in fragments)
    )


# ---- shapes --------------------------------------------------------------------------------------


def test_se3_exp_of_a_3_vector():
    with raises(ValueError, "SE3", "(*batch, 6)", "(3,)"):
        SE3.exp(jnp.zeros(3))


def test_se3_acting_on_a_planar_cloud():
    with raises(ValueError, "(*batch, 3)", "(10, 2)"):
        SE3.identity() @ jnp.zeros((10, 2))


def test_exp_wrong_tangent_length(spec):
    G = spec.cls
    for shape in [(G.tangent_dim + 1,), (5, G.tangent_dim + 2), ()]:
        with raises(ValueError, G.__name__, f"(*batch, {G.tangent_dim})", str(shape)):
            G.exp(jnp.zeros(shape))


def test_wrong_parameter_length(spec):
    G = spec.cls
    with raises(ValueError, f"(*batch, {G.parameters_dim})", G.parameters_layout):
        G(jnp.zeros((4, G.parameters_dim + 1)))
    with raises(ValueError, f"(*batch, {G.parameters_dim})"):
        G(jnp.zeros(()))


def test_act_wrong_point_dimension(spec):
    G = spec.cls
    wrong = 5 - G.space_dim  # 3 for planar groups, 2 for spatial ones
    with raises(ValueError, f"(*batch, {G.space_dim})", f"(7, {wrong})"):
        G.identity() @ jnp.zeros((7, wrong))
    with raises(ValueError, f"(*batch, {G.space_dim})"):
        G.identity().act(jnp.zeros((7, wrong)))


def test_matrix_shapes(spec):
    G = spec.cls
    n = G.matrix_dim
    with raises(ValueError, f"(*batch, {n}, {n})", f"({n + 1}, {n + 1})"):
        G.from_matrix(jnp.eye(n + 1))
    with raises(ValueError, f"(*batch, {n}, {n})"):
        G.from_matrix(jnp.zeros(n))
    with raises(ValueError, f"(*batch, {n}, {n})"):
        G.vee(jnp.zeros((2, n, n + 1)))
    with raises(ValueError, f"(*batch, {G.tangent_dim})"):
        G.hat(jnp.zeros(G.tangent_dim + 1))


def test_tangent_map_shapes(spec):
    G = spec.cls
    bad = jnp.zeros((2, G.tangent_dim + 1))
    for method in (
        G.right_jacobian,
        G.right_jacobian_inverse,
        G.left_jacobian,
        G.left_jacobian_inverse,
    ):
        with raises(ValueError, f"(*batch, {G.tangent_dim})"):
            method(bad)
    x = G.identity()
    with raises(ValueError, f"(*batch, {G.tangent_dim})"):
        x.rplus(jnp.zeros(G.tangent_dim + 1))


def test_non_broadcasting_batch_shapes(spec):
    G = spec.cls
    x, y = G.identity((3,)), G.identity((4,))
    for operation in (
        lambda: x @ y,
        lambda: x.between(y),
        lambda: x.rminus(y),
        lambda: x.interpolate(y, 0.5),
    ):
        with raises(ValueError, "(3,)", "(4,)", "broadcast"):
            operation()
    with raises(ValueError, "(3,)", "(4,)", "broadcast"):
        x @ jnp.zeros((4, G.space_dim))
    with raises(ValueError, "broadcast"):
        x.rplus(jnp.zeros((4, G.tangent_dim)))


def test_errors_are_raised_under_jit(spec):
    G = spec.cls
    with raises(ValueError, f"(*batch, {G.tangent_dim})"):
        jax.jit(G.exp)(jnp.zeros(G.tangent_dim + 1))
    with raises(ValueError, "broadcast"):
        jax.jit(lambda a, b: a @ b)(G.identity((3,)), G.identity((2,)))


# ---- dtypes and types ----------------------------------------------------------------------------


def test_integer_dtypes(spec):
    G = spec.cls
    with raises(TypeError, "floating", "int"):
        G.exp(jnp.zeros(G.tangent_dim, dtype=jnp.int32))
    with raises(TypeError, "floating"):
        G(np.zeros(G.parameters_dim, dtype=np.int64))
    with raises(TypeError, "floating"):
        G.identity() @ np.zeros(G.space_dim, dtype=np.int64)
    with raises(TypeError, "floating"):
        G.from_matrix(np.eye(G.matrix_dim, dtype=np.int64))
    with raises(TypeError, "floating"):
        G.identity().interpolate(G.identity(), np.arange(2))


def test_python_numbers_are_floats(spec):
    """A Python number states no dtype: `interpolate(y, 1)` is `interpolate(y, 1.0)`."""
    G = spec.cls
    x = G.exp(0.3 * jnp.ones(G.tangent_dim))
    np.testing.assert_allclose(
        x.interpolate(G.identity(), 1).parameters(), G.identity().parameters(), atol=1e-6
    )
    np.testing.assert_allclose(
        x.interpolate(G.identity(), 0).parameters(), x.parameters(), atol=1e-6
    )


def test_mixing_groups(spec):
    G = spec.cls
    other = next(s.cls for s in GROUPS if s.cls is not G)
    with raises(TypeError, G.__name__, other.__name__):
        G.identity() @ other.identity()
    with raises(TypeError, G.__name__, other.__name__):
        G.identity().rminus(other.identity())


def test_se_constructors_check_the_rotation():
    with raises(TypeError, "SO3"):
        SE3.from_rotation_and_translation(SO2.identity(), jnp.zeros(3))
    with raises(TypeError, "SO2"):
        SE2.from_rotation_and_translation(SO3.identity(), jnp.zeros(2))
    with raises(ValueError, "(*batch, 3)"):
        SE3.from_rotation_and_translation(SO3.identity(), jnp.zeros(2))


def test_so3_conversions_check_shapes():
    with raises(ValueError, "(*batch, 4)", "xyzw"):
        SO3.from_xyzw(jnp.zeros(3))
    with raises(ValueError, "(*batch, 3)"):
        SO3.from_rotvec(jnp.zeros(4))
    with raises(TypeError, "floating"):
        SO3.from_rpy(np.zeros(2, np.int32), np.zeros(2), np.zeros(2))
    np.testing.assert_array_equal(SO3.from_rpy(0, 0, 0).parameters(), SO3.identity().parameters())


# ---- lieax.jacobian / grad on unsupported pytrees --------------------------------------------------


def test_jacobian_of_integer_leaf_names_its_path():
    tree = {"pose": SE3.identity(), "ids": jnp.arange(3)}
    with raises(TypeError, "argument 0['ids']", "int"):
        lieax.jacobian(lambda t: t["pose"].log())(tree)
    with raises(TypeError, "argument 1[1]"):
        lieax.jacobian(lambda a, b: a.log(), (0, 1))(SO3.identity(), (jnp.ones(2), 3))


def test_jacobian_of_none_leaf_names_its_path():
    with raises(TypeError, "argument 0['mask']", "None"):
        lieax.jacobian(lambda t: t["pose"].log())({"pose": SO3.identity(), "mask": None})


def test_jacobian_of_integer_result_names_its_path():
    with raises(TypeError, "result[1]"):
        lieax.jacobian(lambda x: (x.log(), jnp.arange(2)))(SO3.identity())


def test_jacobian_arguments():
    with raises(ValueError, "mode", "'sideways'"):
        lieax.jacobian(lambda x: x.log(), mode="sideways")
    with raises(ValueError, "argnums"):
        lieax.jacobian(lambda x: x.log(), argnums=3)(SO3.identity())


def test_grad_needs_a_scalar():
    with raises(TypeError, "scalar", "(3,)"):
        lieax.grad(lambda x: x.log())(SO3.identity())
    with raises(TypeError, "scalar", "SO3"):
        lieax.grad(lambda x: x)(SO3.identity())


def test_manifold_helpers_check_their_input():
    tree = {"pose": SE2.identity(), "v": jnp.zeros(2)}
    with raises(ValueError, "5 entries", "(6,)"):
        lieax.unflatten_tangents(tree, jnp.zeros(6))
    with raises(TypeError, "tree['n']"):
        lieax.zero_tangents({"n": jnp.arange(2)})
    with raises(TypeError, "None"):
        lieax.tangent_dim({"pose": SE2.identity(), "x": None})


def test_unflatten_tangents_rejects_a_short_vector():
    tree = {"pose": SE2.identity(), "v": jnp.zeros(2)}
    with raises(ValueError, "5 entries", "(4,)"):
        lieax.unflatten_tangents(tree, jnp.zeros(4))


# ---- what users of other libraries pass (issue 32) -----------------------------------------------


def test_factor_graph_input_from_other_habits():
    """A residual returning a tuple, data as nested lists, raw (x, y, θ) rows where the residual
    wants SE2, float32 data with float64 variables: errors naming the factor kind (lists are
    converted)."""
    from lieax.factorgraph import Factor, FactorGraph, Var

    poses = Var(SE2.exp(jnp.zeros((3, 3))), fixed=[0], name="poses")
    i, j = np.array([0, 1]), np.array([1, 2])

    def between(a, b, z):
        return z.between(a.between(b)).log()

    def both(a, b):
        return a.between(b).log(), a.log()

    with raises(ValueError, "'odometry'", "must return one array (k,)", "tuple"):
        FactorGraph([Factor(both, (poses[i], poses[j]), name="odometry")])
    rows = [[1.0, 0.0, 0.1], [1.0, 0.0, 0.1]]
    factor = Factor(between, (poses[i], poses[j]), rows, name="odometry")
    assert isinstance(factor.data, np.ndarray) and factor.data.shape == (2, 3)
    with raises(ValueError, "'odometry'", "has no attribute between", "float64[3]", "lieax group"):
        FactorGraph([factor])
    planar = Factor(lambda x, p: x.translation() - p, (poses[np.arange(3)],), [[0.0, 1.0]] * 3)
    assert FactorGraph([planar], check_gauge=False).residual_dims == (2,)
    narrow = np.zeros((3, 2), np.float32)
    gps = Factor(lambda x, p: x.translation() - p, (poses[np.arange(3)],), narrow, name="gps")
    with raises(ValueError, "'gps': data", "float32", "variables have dtype float64"):
        FactorGraph([gps], check_gauge=False)


def test_foreign_types_name_their_conversion():
    """A jaxlie group where lieax wants its own, an Open3D cloud where ICP wants points."""
    from lieax.factorgraph import Factor, Var

    jaxlie = pytest.importorskip("jaxlie")
    pose = jaxlie.SE3.exp(jnp.zeros((3, 6)))
    with raises(TypeError, "Var 'poses' value", "jaxlie.SE3", "lieax.SE3(x.parameters())"):
        Var(pose, name="poses")
    with raises(TypeError, "jaxlie.SE3", "lieax.SE3(x.parameters())"):
        lieax.SE3(pose)
    converted = lieax.SE3(pose.parameters())
    np.testing.assert_allclose(converted.parameters(), pose.wxyz_xyz)
    poses = Var(converted, name="poses")
    with raises(TypeError, "Factor 'prior': data", "jaxlie.SE3"):
        Factor(lambda x, z: z.between(x).log(), (poses[np.arange(3)],), pose, name="prior")

    o3d = pytest.importorskip("open3d")
    cloud = o3d.geometry.PointCloud()
    cloud.points = o3d.utility.Vector3dVector(np.random.default_rng(0).normal(size=(20, 3)))
    with raises(TypeError, "source", "Open3D PointCloud", "np.asarray(cloud.points)"):
        lieax.icp.point_to_point(cloud, cloud, max_correspondence_distance=1.0)
