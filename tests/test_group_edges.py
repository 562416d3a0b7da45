"""Edge cases of the groups' constructors and shared operations (issue 17), float64 and float32:

- `Sim3` scales that are not positive and finite are a `ValueError` when concrete, NaN under `jit`;
  `align` of fewer than 3 points or with unusable weights is a `ValueError` naming the count or the
  problem (all-zero weights under `jit`: NaN, never a silent identity);
- Python and NumPy numbers take the group's dtype (`interpolate`, `from_xy_theta`, `from_rpy`,
  Sim3's scale), also under `jit`, `lieax.jacobian` and `jax.grad`; arrays of another float dtype
  are a `TypeError` naming both dtypes (before: JAX's internal error under `lieax.jacobian`);
- S2's basis is orthonormal and tangent to rounding at 1e-8 ... 1e-4 from the former singular
  point $-r$ in both dtypes, with bounded derivatives there, and its Jacobians are exact on both
  sides of the switching circle between its two charts;
- batch shapes that do not broadcast are a `ValueError` naming the entry point and the shapes;
- `align`'s second derivatives (through the implicit rule of the rotation) match finite
  differences of its first derivatives.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import lieax
from lieax import SE2, SE3, SO2, SO3, Sim3
from lieax.groups import S2
from lieax.groups import _s2 as s2

GROUPS = [SO2, SE2, SO3, SE3, Sim3]
IDS = [g.__name__ for g in GROUPS]
DTYPES = [jnp.float64, jnp.float32]
DTYPE_IDS = ["float64", "float32"]


def pair(group, dtype):
    """Two elements: the same values in both dtypes (float32 ones rounded from float64)."""
    return tuple(
        group(group.sample_uniform(jax.random.PRNGKey(k)).parameters().astype(dtype))
        for k in (1, 2)
    )


# ---- Sim3 scales and align's inputs ---------------------------------------------------------------


@pytest.mark.parametrize("dtype", DTYPES, ids=DTYPE_IDS)
@pytest.mark.parametrize("bad", [-1.0, 0.0, np.inf, np.nan])
def test_sim3_scale_must_be_positive(bad, dtype):
    rotation, translation = SO3.identity(dtype=dtype), jnp.zeros(3, dtype)
    with pytest.raises(ValueError, match="Sim3.from_scale scale must be positive and finite"):
        Sim3.from_scale(jnp.asarray(bad, dtype))
    with pytest.raises(ValueError, match="Sim3.from_scale scale"):
        Sim3.from_scale(bad)
    with pytest.raises(ValueError, match="from_rotation_translation_scale scale must be positive"):
        Sim3.from_rotation_translation_scale(rotation, translation, bad)
    with pytest.raises(ValueError, match=r"positive and finite, got .* \(and 1 more\)"):
        Sim3.from_rotation_translation_scale(
            SO3.identity((3,), dtype), translation, jnp.asarray([2.0, bad, bad], dtype)
        )
    with pytest.raises(ValueError, match="scale must be positive"):
        Sim3.from_se3(SE3.identity(dtype=dtype), bad)


def test_sim3_traced_scale_gives_nan():
    """Under `jit` the scale cannot be checked: a negative one gives NaN, as documented."""
    out = jax.jit(lambda s: Sim3.from_scale(s).act(jnp.ones(3)))(jnp.asarray([2.0, -1.0]))
    np.testing.assert_allclose(out[0], 2.0)
    assert np.all(np.isnan(out[1]))
    assert Sim3.from_scale(0.5).scale() == 0.5


@pytest.mark.parametrize("dtype", DTYPES, ids=DTYPE_IDS)
@pytest.mark.parametrize("with_scale", [False, True], ids=["SE3", "Sim3"])
def test_align_rejects_unusable_inputs(with_scale, dtype):
    name = "Sim3.align" if with_scale else "SE3.align"
    points = jnp.asarray(np.random.default_rng(0).normal(size=(5, 3)), dtype)
    for count in (0, 1, 2):
        with pytest.raises(ValueError, match=rf"{name} needs at least 3 .* got {count}\."):
            lieax.align(points[:count], points[:count], with_scale=with_scale)
    with pytest.raises(ValueError, match=f"{name}: the weights of a point set are all zero"):
        lieax.align(points, points, jnp.zeros(5, dtype), with_scale=with_scale)
    with pytest.raises(ValueError, match="all zero"):  # one set of a batch
        lieax.align(points, points, jnp.asarray([[1.0] * 5, [0.0] * 5], dtype))
    with pytest.raises(ValueError, match="nonnegative and finite"):
        lieax.align(points, points, jnp.asarray([1.0, -1.0, 1.0, 1.0, 1.0], dtype))
    other = jnp.float32 if dtype == jnp.float64 else jnp.float64
    with pytest.raises(TypeError, match=f"{name} points: arguments of different dtypes"):
        lieax.align(points, points.astype(other), with_scale=with_scale)
    with pytest.raises(TypeError, match=f"{name} weights has dtype {jnp.dtype(other)}"):
        lieax.align(points, points, jnp.ones(5, other), with_scale=with_scale)
    with pytest.raises(ValueError, match="points_b has non-finite entries"):
        lieax.align(points, points.at[2, 1].set(jnp.nan), with_scale=with_scale)
    # traced: not checked, and the result is NaN (not the identity)
    aligned = jax.jit(lambda w: lieax.align(points, points + 1.0, w, with_scale=with_scale))
    assert np.all(np.isnan(aligned(jnp.zeros(5, dtype)).parameters()))
    good = aligned(jnp.ones(5, dtype))
    assert good.dtype == dtype
    np.testing.assert_allclose(good.act(points + 1.0), points, atol=1e-4)


# ---- dtypes -----------------------------------------------------------------------------------------


NUMBERS = {
    "python": 0.3,
    "int": 1,
    "numpy32": np.float32(0.3),
    "numpy64": np.float64(0.3),
    "numpy0d": np.array(0.3),
    "weak": jnp.asarray(0.3),
}


def interpolation_results(group, x, y, t, numbers):
    """`X.interpolate(Y, t)` and its `lieax.jacobian`s with `t` each of `numbers` and `t` itself
    (traced under `jit`), and a `jax.grad` through the raw parameters."""

    def residual(x_, t_):
        return x_.interpolate(y, t_).log()

    out = {f"jacobian {k}": lieax.jacobian(residual)(x, v) for k, v in numbers.items()}
    out["jacobian traced"] = lieax.jacobian(residual)(x, t)
    out["value"] = x.interpolate(y, t).parameters()
    out["grad"] = jax.grad(lambda p: jnp.sum(residual(group(p), 0.3) ** 2))(x.parameters())
    return out


def traced_dtypes(group, dtype, numbers):
    x, y = pair(group, dtype)
    shapes = jax.eval_shape(lambda x_, t: interpolation_results(group, x_, y, t, numbers), x, 0.3)
    return {key: shape.dtype for key, shape in shapes.items()}


@pytest.mark.parametrize("group", GROUPS, ids=IDS)
def test_numbers_take_the_group_dtype(group):
    """float32 elements stay float32 with a number for `t`, under `jit`, `lieax.jacobian` and
    `jax.grad` (before: float64 parameters, and JAX's internal error under `lieax.jacobian`); SO2
    with every kind of number, in both dtypes. Traced only (`jax.eval_shape`): the failure was at
    trace time, and the code path is the same for every group."""
    numbers = NUMBERS if group is SO2 else {"python": 0.3}
    for dtype in DTYPES if group is SO2 else [jnp.float32]:
        for key, result in traced_dtypes(group, dtype, numbers).items():
            assert result == dtype, (dtype, key)


@pytest.fixture(scope="module")
def interpolation_values():
    return jax.jit(
        lambda x, y, t: interpolation_results(SO3, x, y, t, {"numpy32": np.float32(0.3)})
    )


def test_float32_interpolation_values(interpolation_values):
    """The float32 values and Jacobians are float64's, rounded."""
    out32 = interpolation_values(*pair(SO3, jnp.float32), 0.3)
    out64 = interpolation_values(*pair(SO3, jnp.float64), 0.3)
    for key, value in out32.items():
        np.testing.assert_allclose(value, out64[key], atol=1e-5, rtol=1e-5, err_msg=key)
    np.testing.assert_allclose(out64["jacobian traced"], out64["jacobian numpy32"], atol=1e-7)


def test_constructor_numbers_take_the_array_dtype():
    f32 = jnp.float32
    assert SE2.from_xy_theta(jnp.float32(1.0), jnp.float32(2.0), 0.5).dtype == f32
    assert SE2.from_xy_theta(jnp.ones(3, f32), np.float64(2.0), 0).dtype == f32
    assert SO3.from_rpy(jnp.float32(1.0), jnp.float32(2.0), 0.5).dtype == f32
    assert SO3.from_rpy(0.1, np.float32(0.2), jnp.zeros((2, 1), f32)).batch_shape == (2, 1)
    assert SO3.from_rpy(0, 0, 0).dtype == jnp.float64
    rotation = SO3.identity(dtype=f32)
    assert Sim3.from_rotation_translation_scale(rotation, jnp.zeros(3, f32), 2.0).dtype == f32
    assert Sim3.from_rotation_translation_scale(rotation, np.zeros(3, f32), 2).dtype == f32
    assert Sim3.from_se3(SE3.identity(dtype=f32), np.float64(3.0)).dtype == f32
    assert Sim3.from_scale(np.float32(2.0)).dtype == f32
    # the values are those of float64, rounded
    np.testing.assert_allclose(
        SO3.from_rpy(jnp.float32(0.1), 0.2, 0.3).parameters(),
        SO3.from_rpy(0.1, 0.2, 0.3).parameters(),
        atol=1e-7,
    )
    with pytest.raises(TypeError, match="SE2.from_xy_theta: arguments of different dtypes"):
        SE2.from_xy_theta(jnp.zeros(2, f32), jnp.zeros(2), 0.0)
    with pytest.raises(TypeError, match="float32 and float64"):
        SO3.from_rpy(jnp.zeros(2, f32), jnp.zeros(2), 0.0)
    with pytest.raises(TypeError, match="translation has dtype float64 but the rotation"):
        SE3.from_rotation_and_translation(rotation, jnp.zeros(3))
    with pytest.raises(
        TypeError, match="scale has dtype float64 but the rotation has dtype float32"
    ):
        Sim3.from_rotation_translation_scale(rotation, jnp.zeros(3, f32), jnp.asarray([2.0]))


@pytest.mark.parametrize("group", GROUPS, ids=IDS)
def test_dtype_mismatch_is_a_lieax_error(group):
    """Arrays of another float dtype: a `TypeError` naming both dtypes, eagerly, under `jit` and
    under `lieax.jacobian` (before: JAX's 'linearized function called on tangent values
    inconsistent with the original primal values')."""
    x32, _ = pair(group, jnp.float32)
    x64, y64 = pair(group, jnp.float64)
    both = r"float(64|32).*float(32|64)"
    with pytest.raises(TypeError, match=rf"{group.__name__}.compose: dtypes {both}"):
        lieax.jacobian(lambda y: x64.compose(y).log())(x32)
    with pytest.raises(TypeError, match=rf"{group.__name__}.rminus: dtypes {both}"):
        jax.jit(lambda y: y.rminus(x64))(x32)
    with pytest.raises(TypeError, match=f"{group.__name__}.interpolate: dtypes {both}"):
        x32.interpolate(y64, 0.5)
    with pytest.raises(
        TypeError, match=f"interpolate t has dtype float64 but the {group.__name__}"
    ):
        lieax.jacobian(lambda x: x.interpolate(x, jnp.asarray([0.5])))(x32)
    with pytest.raises(TypeError, match="rplus tangent has dtype float32 but .* has dtype float64"):
        x64.rplus(jnp.zeros(group.tangent_dim, jnp.float32))
    with pytest.raises(TypeError, match="acting on points has dtype float64 but .* float32"):
        jax.grad(lambda p: jnp.sum(group(p).act(jnp.ones(group.space_dim))))(x32.parameters())
    # numbers are not mismatches: a NumPy float32 scalar in a float64 residual
    residual = lieax.jacobian(lambda x: x.rplus(np.float32(0.5) * x.log()).log())
    assert jax.eval_shape(residual, x64).dtype == jnp.float64


# ---- S2's basis -------------------------------------------------------------------------------------

_R = np.asarray(s2.REFERENCE)


def _unit(v):
    return v / np.linalg.norm(v, axis=-1, keepdims=True)


def _approaches():
    """Directions 1e-8 ... 1e-4 (angle) from -r, approached from 6 directions around it."""
    helper = _unit(np.cross(_R, [1.0, 0.0, 0.0]))
    around = [np.cos(a) * helper + np.sin(a) * np.cross(_R, helper) for a in np.arange(6)]
    points = [
        _unit(-_R * np.cos(d) + np.sin(d) * u)
        for d in (1e-8, 1e-7, 1e-6, 1e-5, 1e-4)
        for u in around
    ]
    return np.stack([-_R, *points])


@pytest.fixture(scope="module")
def basis_and_derivative():
    return jax.jit(jax.vmap(lambda p: (s2.basis(p), jax.jacfwd(s2.basis)(p))))


@pytest.mark.parametrize("dtype", DTYPES, ids=DTYPE_IDS)
def test_s2_basis_near_former_singular_point(dtype, basis_and_derivative):
    """Orthonormal and tangent to rounding (before: ~1e-8 off at 1e-8 from -r in float64, ~2e-2 at
    1e-6 in float32), right-handed, and with bounded derivatives (before: ~1/distance)."""
    points = jnp.asarray(_approaches(), dtype)
    bases, derivatives = basis_and_derivative(points)
    assert bases.dtype == dtype
    b = np.asarray(bases, np.float64)
    p = np.asarray(points, np.float64)
    eps = float(jnp.finfo(dtype).eps)
    gram = np.swapaxes(b, -1, -2) @ b - np.eye(2)
    assert np.max(np.abs(gram)) < 4 * eps
    assert np.max(np.abs(np.einsum("nij,ni->nj", b, p))) < 4 * eps
    np.testing.assert_allclose(np.cross(b[..., 0], b[..., 1]), p, atol=4 * eps)
    assert np.all(np.isfinite(np.asarray(derivatives))) and np.max(np.abs(derivatives)) < 5.0


@pytest.fixture(scope="module")
def s2_jacobians():
    """Jitted local Jacobians of `q ⊖ p` (in p and q) and of `p ⊕ ξ` (in p)."""

    def one(p, q, xi):
        return {
            "rminus_p": lieax.jacobian(lambda p_: q.rminus(p_))(p),
            "rminus_q": lieax.jacobian(lambda q_: q_.rminus(p))(q),
            "rplus_p": lieax.jacobian(lambda p_: p_.rplus(xi))(p),
        }

    return jax.jit(jax.vmap(one))


def test_s2_jacobians_on_both_sides_of_the_switch(s2_jacobians):
    r"""At 1e-4 inside and outside the switching circle ($1 + r^\top p = 0.3$), the local Jacobians
    match central differences (steps of 1e-7 do not cross the circle); the basis there is each
    chart's, so it jumps across the circle but is orthonormal on both sides."""
    helper = _unit(np.cross(_R, [0.0, 0.0, 1.0]))
    ps = []
    for a in (0.3, 2.0, 4.5):
        u = np.cos(a) * helper + np.sin(a) * np.cross(_R, helper)
        for side in (-1e-4, 1e-4):
            c = s2.SWITCH - 1.0 + side  # r·p
            ps.append(c * _R + np.sqrt(1.0 - c * c) * u)
    ps = np.stack(ps)
    rng = np.random.default_rng(3)
    xis = 0.2 * rng.normal(size=(len(ps), 2))
    p = S2(jnp.asarray(ps))
    q = p.rplus(jnp.asarray(0.3 * rng.normal(size=(len(ps), 2))))
    out = s2_jacobians(p, q, jnp.asarray(xis))
    bases = np.asarray(p.basis())
    jump = np.abs(bases[0::2] - bases[1::2]).max()
    assert jump > 0.1  # the two charts differ there ...
    np.testing.assert_allclose(
        np.swapaxes(bases, -1, -2) @ bases, np.eye(2)[None].repeat(6, 0), atol=1e-15
    )

    def central(f, at, step=1e-7):
        columns = [
            (f(at.rplus(step * e)) - f(at.rplus(-step * e))) / (2 * step) for e in jnp.eye(2)
        ]
        return np.stack([np.asarray(c) for c in columns], axis=-1)

    expected = {
        "rminus_p": central(lambda p_: q.rminus(p_), p),
        "rminus_q": central(lambda q_: q_.rminus(p), q),
        "rplus_p": central(
            lambda p_: p_.rplus(jnp.asarray(xis)).rminus(p.rplus(jnp.asarray(xis))), p
        ),
    }
    for name, jac in out.items():  # ... and each side's Jacobians are its own chart's, exactly
        np.testing.assert_allclose(np.asarray(jac), expected[name], atol=1e-7, err_msg=name)


# ---- batch shapes -----------------------------------------------------------------------------------


def test_batch_shapes_that_do_not_broadcast():
    two, three = jnp.zeros(2), jnp.zeros(3)
    cases = {
        "SE3.from_rotation_and_translation": lambda: SE3.from_rotation_and_translation(
            SO3.identity((2,)), jnp.zeros((3, 3))
        ),
        "SE3.interpolate": lambda: SE3.identity((2,)).interpolate(SE3.identity((2,)), three),
        "SE2.from_xy_theta": lambda: SE2.from_xy_theta(two, three, 0.0),
        "SO3.from_rpy": lambda: SO3.from_rpy(two, 0.0, three),
        "Sim3.from_rotation_translation_scale": lambda: Sim3.from_rotation_translation_scale(
            SO3.identity((2,)), jnp.zeros((3, 3))
        ),
        "S2.rplus": lambda: S2.from_vector(jnp.ones((2, 3))).rplus(jnp.zeros((3, 2))),
        "S2.rminus": lambda: S2.from_vector(jnp.ones((2, 3))).rminus(
            S2.from_vector(jnp.ones((3, 3)))
        ),
        "S2.rotate": lambda: S2.from_vector(jnp.ones((2, 3))).rotate(SO3.identity((3,))),
    }
    for name, call in cases.items():
        with pytest.raises(ValueError, match=rf"{name}: batch shapes .*\(2,\).*\(3,\).* do not"):
            call()
    # shapes that broadcast still do
    assert SE3.identity().interpolate(SE3.identity(), jnp.linspace(0, 1, 3)).batch_shape == (3,)
    assert SE2.from_xy_theta(jnp.zeros((2, 1)), three, 0.0).batch_shape == (2, 3)
    assert S2.from_vector(jnp.ones(3)).rotate(SO3.identity((4,))).batch_shape == (4,)


# ---- align's second derivatives ---------------------------------------------------------------------


@pytest.mark.parametrize("with_scale", [False, True], ids=["SE3", "Sim3"])
def test_align_second_derivatives(with_scale):
    """The Hessian of a scalar of the alignment with respect to `points_a` (forward over reverse,
    through the rotation's implicit rule) against central differences of its gradient."""
    rng = np.random.default_rng(8)
    b = rng.normal(size=(5, 3)) * np.array([2.0, 1.0, 0.5])
    a = 1.3 * b @ SO3.exp(jnp.array([0.3, -0.5, 1.1])).as_matrix().T + 0.1 * rng.normal(size=(5, 3))
    weights = jnp.asarray(rng.uniform(0.5, 2.0, size=5))
    coefficients = jnp.asarray(rng.normal(size=(3, 4)))

    def scalar(points_a):
        matrix = lieax.align(points_a, jnp.asarray(b), weights, with_scale=with_scale).as_matrix()
        return jnp.sum(coefficients * matrix[:3, :])

    gradient = jax.jit(jax.grad(scalar))
    hessian = np.asarray(jax.jit(jax.hessian(scalar))(jnp.asarray(a))).reshape(15, 15)
    step = 1e-5
    columns = [
        (gradient(jnp.asarray(a + step * e)) - gradient(jnp.asarray(a - step * e))) / (2 * step)
        for e in np.eye(15).reshape(15, 5, 3)
    ]
    expected = np.stack([np.asarray(c).ravel() for c in columns], axis=-1)
    np.testing.assert_allclose(hessian, expected, atol=1e-7)
    np.testing.assert_allclose(hessian, hessian.T, atol=1e-10)
