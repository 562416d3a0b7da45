r"""SE23 (extended poses) against GTSAM's `NavState`, and the group protocol's kernel check.

The registry (`tests/registry.py`) gives SE23 the whole group suite (values against matrix
formulas, every Jacobian against finite differences); here the same group is compared with an
independent implementation: GTSAM 4.3's `NavState`, whose matrix is lieax's $[R, p, v; 0, I_2]$
and whose tangent is $(\delta R, \delta p, \delta v)$ (`lieax.conventions.se23_tangent_*`).
Skipped without gtsam.
"""

import types

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import lieax
from lieax import SE3, SE23
from lieax import conventions as cv
from lieax.groups import _se23
from lieax.groups._base import KERNELS, AbstractGroup

gtsam = pytest.importorskip("gtsam")

ATOL = 1e-10


def _tangents():
    """Tangents with angles from 0 to near π (lieax order), translations of order 1-5."""
    rng = np.random.default_rng(23)
    xis = []
    for angle in (0.0, 1e-5, 0.4, 1.7, 3.0):
        axis = rng.normal(size=3)
        xi = rng.normal(size=9) * 2.0
        xi[3:6] = angle * axis / np.linalg.norm(axis)
        xis.append(xi)
    return np.stack(xis)


XIS = _tangents()
OTHERS = np.roll(XIS, 1, axis=0) * np.array([1, -1, 1, 0.5, 0.5, 0.5, -1, 1, 1])


def _nav(xi):
    return gtsam.NavState.Expmap(cv.se23_tangent_to_gtsam(xi).__array__())


def _matrices(x):
    return np.stack([np.asarray(m) for m in x])


@pytest.fixture(scope="module")
def lieax_results():
    """Values and Jacobians of every operation compared, batched over XIS, one jitted call."""

    def single(xi, eta):
        x, y = SE23.exp(xi), SE23.exp(eta)
        jac = lambda f, *args: lieax.jacobian(f, argnums=tuple(range(len(args))))(*args)  # noqa: E731
        return dict(
            exp=x.as_matrix(),
            log=x.log(),
            compose=(x @ y).as_matrix(),
            inverse=x.inverse().as_matrix(),
            adjoint=x.adjoint(),
            exp_jacobian=lieax.jacobian(SE23.exp)(xi),
            log_jacobian=lieax.jacobian(lambda g: g.log())(x),
            rminus_jacobians=jac(lambda a, b: b.rminus(a), x, y),
            rplus_jacobians=jac(lambda a, d: a.rplus(d), x, eta),
        )

    return jax.jit(jax.vmap(single))(jnp.asarray(XIS), jnp.asarray(OTHERS))


def test_values_match_navstate(lieax_results):
    """Exp, Log, compose, inverse and the adjoint matrix equal NavState's (after permuting)."""
    for i, (xi, eta) in enumerate(zip(XIS, OTHERS)):
        x, y = _nav(xi), _nav(eta)
        np.testing.assert_allclose(lieax_results["exp"][i], x.matrix(), atol=ATOL)
        log = cv.se23_tangent_from_gtsam(gtsam.NavState.Logmap(x))
        np.testing.assert_allclose(lieax_results["log"][i], log, atol=ATOL)
        np.testing.assert_allclose(lieax_results["compose"][i], x.compose(y).matrix(), atol=ATOL)
        np.testing.assert_allclose(lieax_results["inverse"][i], x.inverse().matrix(), atol=ATOL)
        adjoint = cv.se23_jacobian_from_gtsam(x.AdjointMap())
        np.testing.assert_allclose(lieax_results["adjoint"][i], adjoint, atol=ATOL)


def test_jacobians_match_navstate(lieax_results):
    """The Jacobians of Exp, Log, rminus (`logmap`) and rplus (`expmap`) equal GTSAM's `H`
    blocks after permuting rows and columns. (NavState's `retract` and `localCoordinates` are a
    different chart in 4.3, componentwise `(R Exp(δR), p + R δp, v + R δv)`,
    so they are not compared.)"""
    for i, (xi, eta) in enumerate(zip(XIS, OTHERS)):
        x, y = _nav(xi), _nav(eta)
        h_exp, h_log = np.zeros((9, 9)), np.zeros((9, 9))
        gtsam.NavState.Expmap(cv.se23_tangent_to_gtsam(xi).__array__(), h_exp)
        gtsam.NavState.Logmap(x, h_log)
        h1, h2, h3, h4 = (np.zeros((9, 9)) for _ in range(4))
        x.logmap(y, h1, h2)
        x.expmap(cv.se23_tangent_to_gtsam(eta).__array__(), h3, h4)
        expected = {
            "exp_jacobian": h_exp,
            "log_jacobian": h_log,
            "rminus_jacobians": (h1, h2),
            "rplus_jacobians": (h3, h4),
        }
        for name, h in expected.items():
            blocks = h if isinstance(h, tuple) else (h,)
            actuals = lieax_results[name] if isinstance(h, tuple) else (lieax_results[name],)
            for actual, block in zip(actuals, blocks):
                np.testing.assert_allclose(
                    actual[i], cv.se23_jacobian_from_gtsam(block), atol=1e-8, err_msg=name
                )


def test_pose_rotation_and_velocity_share_the_carrier():
    """`pose()`, `rotation()` and `velocity()` read the extended pose's parts, with derivatives
    (the first seven carrier entries are SE3's carrier)."""
    xi = jnp.asarray(XIS[3])
    x = SE23.exp(xi)
    expected = SE3.exp(xi[:6])  # Exp's rotation and position blocks are SE3's
    np.testing.assert_allclose(x.pose().as_matrix(), expected.as_matrix(), atol=1e-12)
    jac_pose = lieax.jacobian(lambda g: g.pose())(x)
    np.testing.assert_allclose(jac_pose, np.eye(9)[:6], atol=1e-12)
    jac_velocity = lieax.jacobian(lambda g: g.velocity())(x)
    rotation = np.asarray(x.rotation().as_matrix())
    np.testing.assert_allclose(jac_velocity, np.hstack([np.zeros((3, 6)), rotation]), atol=1e-12)
    back = SE23.from_pose_and_velocity(x.pose(), x.velocity())
    np.testing.assert_allclose(back.as_matrix(), x.as_matrix(), atol=1e-12)


def test_tangent_converters_round_trip():
    xi = jnp.asarray(XIS)
    np.testing.assert_array_equal(cv.se23_tangent_from_gtsam(cv.se23_tangent_to_gtsam(xi)), xi)
    np.testing.assert_array_equal(cv.se23_tangent_to_gtsam(xi)[..., :3], xi[..., 3:6])
    with pytest.raises(ValueError, match="9"):
        cv.se23_tangent_to_gtsam(xi[..., :6])


def test_a_missing_kernel_fails_at_class_creation():
    """The group protocol: a kernel namespace without `log` is a TypeError naming it when the
    class is created, not an AttributeError at first use."""
    complete = types.SimpleNamespace(**{name: getattr(_se23, name) for name in KERNELS})
    partial = types.SimpleNamespace(**{n: getattr(_se23, n) for n in KERNELS if n != "log"})

    class Complete(AbstractGroup):
        kernels = complete
        tangent_dim, parameters_dim, space_dim, matrix_dim = 9, 10, 3, 5
        parameters_layout = "wxyz, p, v"

    assert Complete._log.__wrapped__ is _se23.log  # (compiled when called eagerly, lieax._eager)
    with pytest.raises(TypeError, match="lacks the group kernels log"):

        class Broken(AbstractGroup):
            kernels = partial


@pytest.mark.parametrize(
    "group", [lieax.SO2, lieax.SE2, lieax.SO3, SE3, lieax.Sim3, SE23], ids=lambda g: g.__name__
)
def test_second_derivatives_through_parameters(group):
    """The Hessian of a function of `parameters()` (and of a composition read through it) matches
    finite differences of its gradient. The carrier maps once normalized raw quaternions with the
    carrier kernel `so3.normalize`, which reads a raw derivative as a carrier: SE3's and Sim3's
    second derivatives were off by O(1)."""
    rng = np.random.default_rng(7)
    other = group.exp(jnp.asarray(0.7 * rng.normal(size=group.tangent_dim)))
    weights = jnp.arange(1.0, group.parameters_dim + 1)

    def f(xi):
        x = group.exp(xi)
        return jnp.sum(weights * x.parameters() ** 2) + jnp.sum(weights * (x @ other).parameters())

    xi = jnp.asarray(0.7 * rng.normal(size=group.tangent_dim))
    hessian, grad, step = jax.jit(jax.hessian(f))(xi), jax.jit(jax.grad(f)), 1e-5
    columns = [(grad(xi + step * e) - grad(xi - step * e)) / (2 * step) for e in np.eye(xi.size)]
    np.testing.assert_allclose(hessian, np.stack(columns, axis=1), atol=1e-7)
