"""Sim3 and S2: values against matrix formulas, local Jacobians against central finite differences
over regimes that include scale, forward vs reverse mode, batched vs vmapped, raw-parameter
derivatives, second derivatives, NaN-free gradients, and S2 in `lieax.jacobian` and the solver.

Sim3 regimes (tangent $(v, \\omega, \\sigma)$): identity, 1e-9 from it, pure translation, pure scale,
translation and scale, rotation 1e-4, rotation and scale 1e-4 (the joint series of $W$), π - 1e-6
with scale, random, large (translation ×5, angle 2.5-3, scale e^{±2.5}). Finite differences are
taken on 4×4 matrices (`scipy.linalg.expm` of the algebra), independently of lieax.
"""

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
import scipy.linalg
from registry import sim3_hat as hat
from registry import sim3_vee as vee
from registry import skew3 as skew
from scipy.spatial.transform import Rotation

jax.config.update("jax_enable_x64", True)

import lieax
import lieax.lstsq
from lieax.groups import _base
from lieax.groups._s2 import S2, SINGULAR_DIRECTION
from lieax.groups._sim3 import Sim3, w_coefficients

SO3 = lieax.SO3
MANIFOLD_PATCH = hasattr(_base, "AbstractManifold")
needs_manifold_patch = pytest.mark.skipif(
    not MANIFOLD_PATCH,
    reason="S2 as a lieax.jacobian / solver leaf needs AbstractManifold in _base.py (see _s2.py)",
)

FD_STEP, FD_STEP_NEAR_PI = 1e-6, 1e-7
FD_ATOL, FD_RTOL = 1e-6, 1e-6
VALUE_ATOL = 1e-10


# ---- NumPy reference for Sim3 (hat, vee, skew: tests/registry.py) ----------------------------------


_NODES, _WEIGHTS = np.polynomial.legendre.leggauss(40)
_TAU, _WEIGHTS = 0.5 * (_NODES + 1.0), 0.5 * _WEIGHTS


def expm(xi):
    """$\\exp(\\xi^\\wedge) = [e^\\sigma R, W v; 0, 1]$ with $R$ from SciPy's rotation vector and
    $W = \\int_0^1 e^{\\sigma\\tau} R(\\tau\\omega)\\,d\\tau$ by 40-point Gauss-Legendre quadrature
    (exact to rounding here; `scipy.linalg.expm` of the 4×4 algebra loses ~5e-13 near π, which
    the logarithm there amplifies beyond the value tolerance)."""
    w = w_quadrature(xi[6], xi[3:6])
    m = np.eye(4)
    m[:3, :3] = np.exp(xi[6]) * Rotation.from_rotvec(xi[3:6]).as_matrix()
    m[:3, 3] = w @ xi[:3]
    return m


def w_quadrature(sigma, omega):
    rotations = Rotation.from_rotvec(_TAU[:, None] * omega).as_matrix()
    return np.einsum("k,kij->ij", _WEIGHTS * np.exp(sigma * _TAU), rotations)


def logm(matrix):
    """The principal logarithm: $\\sigma = \\log\\det(sR)/3$, $\\omega$ by SciPy's rotation vector,
    $v = W(\\sigma, \\omega)^{-1} t$ (well conditioned near π, unlike `scipy.linalg.logm`)."""
    sigma = np.log(np.linalg.det(matrix[:3, :3])) / 3.0
    omega = Rotation.from_matrix(matrix[:3, :3] / np.exp(sigma)).as_rotvec()
    return np.concatenate(
        [np.linalg.solve(w_quadrature(sigma, omega), matrix[:3, 3]), omega, [sigma]]
    )


def log_near_identity(m):
    e = m - np.eye(m.shape[-1])
    power, total = e, e.copy()
    for k in range(2, 8):
        power = power @ e
        total += (-1) ** (k + 1) * power / k
    return total


def act(matrix, p):
    return matrix[:3, :3] @ p + matrix[:3, 3]


def adjoint(matrix):
    inv = np.linalg.inv(matrix)
    return np.stack([vee(matrix @ hat(e) @ inv) for e in np.eye(7)], axis=1)


# ---- regimes ------------------------------------------------------------------------------------

REGIMES = (
    "identity",
    "tiny",
    "translation",
    "scale",
    "translation_scale",
    "small_rotation",
    "small_rotation_scale",
    "near_pi",
    "random",
    "random_large",
)


def regime_tangent(regime, seed=0):
    rng = np.random.default_rng([seed, REGIMES.index(regime)])
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    v = rng.normal(size=3)
    table = {
        "identity": (0 * v, 0.0, 0.0),
        "translation": (v, 0.0, 0.0),
        "scale": (0 * v, 0.0, 0.7),
        "translation_scale": (v, 0.0, -0.6),
        "small_rotation": (v, 1e-4, 0.0),
        "small_rotation_scale": (v, 1e-4, 1e-4),
        "near_pi": (v, np.pi - 1e-6, 0.4),
        "random": (v, rng.uniform(0.3, 2.5), rng.uniform(-1.0, 1.0)),
        "random_large": (5.0 * v, rng.uniform(2.5, 3.0), 2.5 * rng.choice([-1.0, 1.0])),
    }
    if regime == "tiny":
        direction = rng.normal(size=7)
        return 1e-9 * direction / np.linalg.norm(direction)
    v, angle, sigma = table[regime]
    return np.concatenate([v, angle * axis, [sigma]])


def regime_tangents(seed=0):
    return np.stack([regime_tangent(r, seed) for r in REGIMES])


def random_tangents(count, seed, max_angle=3.0):
    rng = np.random.default_rng([seed, 77])
    out = []
    for _ in range(count):
        axis = rng.normal(size=3)
        axis *= rng.uniform(0, max_angle) / np.linalg.norm(axis)
        out.append(np.concatenate([rng.normal(size=3), axis, [rng.uniform(-1, 1)]]))
    return np.stack(out)


# ---- operations: (argument kinds, differentiated args, output kind, lieax, reference) ----------

OPERATIONS = {  # the kernels with closed-form rules; the composites (between, rplus, rminus,
    # interpolate) are base-class code run for every group by the registry tests
    "exp": (("xi",), (0,), "group", lambda xi: Sim3.exp(xi), lambda xi: expm(xi)),
    "log": (("X",), (0,), "array", lambda x: x.log(), lambda x: logm(x)),
    "compose": (("X", "Y"), (0, 1), "group", lambda x, y: x @ y, lambda x, y: x @ y),
    "inverse": (("X",), (0,), "group", lambda x: x.inverse(), np.linalg.inv),
    "act": (("X", "p"), (0, 1), "array", lambda x, p: x @ p, act),
    "adjoint": (("X",), (0,), "array", lambda x: x.adjoint(), adjoint),
    "as_matrix": (("X",), (0,), "array", lambda x: x.as_matrix(), lambda x: x),
    "rminus": (
        ("YX", "Y"),
        (0, 1),
        "array",
        lambda x, y: x.rminus(y),
        lambda x, y: logm(np.linalg.solve(y, x)),
    ),
}


def build_inputs(kinds):
    xis = regime_tangents()
    count = len(xis)
    etas = random_tangents(count, seed=1)
    points = np.random.default_rng(2).normal(size=(count, 3))
    ts = np.linspace(0.15, 0.85, count)
    lieax_args, numpy_args = [], []
    for kind in kinds:
        if kind == "X":
            lieax_args.append(Sim3.exp(jnp.asarray(xis)))
            numpy_args.append([expm(x) for x in xis])
        elif kind == "Y":
            lieax_args.append(Sim3.exp(jnp.asarray(etas)))
            numpy_args.append([expm(e) for e in etas])
        elif kind == "YX":
            lieax_args.append(Sim3.exp(jnp.asarray(etas)) @ Sim3.exp(jnp.asarray(xis)))
            numpy_args.append([expm(e) @ expm(x) for e, x in zip(etas, xis)])
        elif kind == "xi":
            lieax_args.append(jnp.asarray(xis))
            numpy_args.append(list(xis))
        elif kind == "p":
            lieax_args.append(jnp.asarray(points))
            numpy_args.append(list(points))
        else:
            lieax_args.append(jnp.asarray(ts))
            numpy_args.append(list(ts))
    return tuple(lieax_args), [list(e) for e in zip(*numpy_args)]


def fd_blocks(kinds, diff, output, reference, args, step):
    base = reference(*args)
    blocks = []
    for i in diff:
        group = kinds[i] in ("X", "Y", "YX")
        size = 7 if group else int(np.size(args[i]))
        columns = []
        for direction in np.eye(size):
            sides = []
            for sign in (1.0, -1.0):
                moved = list(args)
                if group:
                    moved[i] = args[i] @ expm(sign * step * direction)
                else:
                    moved[i] = args[i] + sign * step * direction.reshape(np.shape(args[i]))
                value = reference(*moved)
                if output == "group":
                    sides.append(vee(log_near_identity(np.linalg.solve(base, value))))
                else:
                    sides.append(np.ravel(value - base))
            columns.append((sides[0] - sides[1]) / (2 * step))
        blocks.append(np.stack(columns, axis=1))
    return blocks


def _as_array(value):
    return value.as_matrix() if isinstance(value, lieax.AbstractGroup) else value


@functools.cache
def results(name):
    """Value and `lieax.jacobian` in both modes on the batch of regimes, in one jitted call."""
    kinds, diff, _output, f, _ = OPERATIONS[name]
    args, per_element = build_inputs(kinds)

    def evaluate(a):
        return {
            "value": _as_array(f(*a)),
            "fwd": lieax.jacobian(f, diff, mode="fwd")(*a),
            "rev": lieax.jacobian(f, diff, mode="rev")(*a),
        }

    out = jax.tree_util.tree_map(np.asarray, jax.jit(evaluate)(args))
    return out, per_element


def split_batched(block, count, out_size):
    """Per-element blocks `(count, out_size, in_size)` of a batched Jacobian block and the largest
    entry coupling different elements."""
    block = np.asarray(block).reshape(count, out_size, count, -1)
    diagonal = block[np.arange(count), :, np.arange(count), :]
    off = block.copy()
    off[np.arange(count), :, np.arange(count), :] = 0.0
    return diagonal, np.max(np.abs(off))


@pytest.mark.parametrize("name", list(OPERATIONS))
def test_sim3_operation(name):
    """Value vs matrix formula and Jacobian vs finite differences at every regime (scale
    included), fwd == rev, batch elements uncoupled."""
    kinds, diff, output, _, reference = OPERATIONS[name]
    out, per_element = results(name)
    count = len(per_element)
    out_size = 7 if output == "group" else int(np.prod(out["value"].shape[1:]))
    for regime, value, args in zip(REGIMES, out["value"], per_element):
        expected = reference(*args)
        scale = max(1.0, np.max(np.abs(expected)))
        np.testing.assert_allclose(
            value,
            expected,
            rtol=0,
            atol=VALUE_ATOL * scale,
            err_msg=f"Sim3.{name} value at {regime}",
        )
    for position, argnum in enumerate(diff):
        what = f"Sim3.{name} d/d(arg {argnum})"
        fwd, rev = out["fwd"][position], out["rev"][position]
        np.testing.assert_allclose(rev, fwd, rtol=1e-12, atol=1e-12, err_msg=f"{what}: rev vs fwd")
        blocks, off = split_batched(fwd, count, out_size)
        assert off == 0.0, f"{what}: batch elements coupled"
        for index, (regime, args) in enumerate(zip(REGIMES, per_element)):
            step = FD_STEP_NEAR_PI if regime == "near_pi" else FD_STEP
            expected = fd_blocks(kinds, diff, output, reference, args, step)[position]
            actual = blocks[index]
            assert np.all(np.isfinite(actual)), f"{what} at {regime}: not finite"
            error = np.max(np.abs(actual - expected))
            bound = FD_ATOL + FD_RTOL * np.max(np.abs(expected))
            assert error <= bound, (
                f"{what} at {regime}: |J - J_fd| = {error:.3g}\n{actual}\n{expected}"
            )


def test_sim3_identities():
    """exp(log X) = X, Ad(XY) = Ad(X)Ad(Y), Jl = Ad(Exp ξ) Jr, Jr Jr⁻¹ = I, Exp(ξ + δ) ≈ Exp(ξ)
    Exp(Jr δ), from_matrix ∘ as_matrix = id, and W's coefficients against their integrals."""
    grid_sigma, grid_theta = np.meshgrid(
        [0.0, 1e-7, -0.9, 1.0, 3.0, -4.0, -30.0, 12.0], [0.0, 1e-6, 0.99, 1.01, 3.1, 8.0, 14.0]
    )
    grid_sigma, grid_theta = grid_sigma.ravel(), grid_theta.ravel()

    @jax.jit
    def evaluate(xis, etas, sigma, s):
        x, y = Sim3.exp(xis), Sim3.exp(etas)
        return {
            "round_trip": Sim3.exp(x.log()).as_matrix(),
            "matrix": x.as_matrix(),
            "ad_product": (x @ y).adjoint(),
            "ad_factors": x.adjoint() @ y.adjoint(),
            "jr": Sim3.right_jacobian(xis),
            "jl": Sim3.left_jacobian(xis),
            "adjoint": x.adjoint(),
            "jr_inverse": Sim3.right_jacobian_inverse(xis),
            "from_matrix": Sim3.from_matrix(x.as_matrix()).as_matrix(),
            "w": jnp.stack(w_coefficients(sigma, s), axis=-1),
        }

    xis = regime_tangents()
    out = jax.tree_util.tree_map(
        np.asarray,
        evaluate(
            jnp.asarray(xis),
            jnp.asarray(random_tangents(len(xis), seed=3)),
            jnp.asarray(grid_sigma),
            jnp.asarray(grid_theta**2),
        ),
    )
    np.testing.assert_allclose(out["round_trip"], out["matrix"], atol=1e-12)
    np.testing.assert_allclose(out["ad_product"], out["ad_factors"], atol=1e-9)
    np.testing.assert_allclose(out["jl"], out["adjoint"] @ out["jr"], atol=1e-10)
    np.testing.assert_allclose(
        out["jr"] @ out["jr_inverse"], np.broadcast_to(np.eye(7), out["jr"].shape), atol=1e-10
    )
    np.testing.assert_allclose(out["from_matrix"], out["matrix"], atol=1e-12)
    step = 1e-6
    for regime, xi, j in zip(REGIMES, xis, out["jr"]):
        columns = []
        for e in np.eye(7):
            plus = np.linalg.solve(expm(xi), expm(xi + step * e))
            minus = np.linalg.solve(expm(xi), expm(xi - step * e))
            columns.append(
                (vee(log_near_identity(plus)) - vee(log_near_identity(minus))) / (2 * step)
            )
        np.testing.assert_allclose(
            j,
            np.stack(columns, axis=1),
            atol=1e-6 * max(1, np.abs(j).max()),
            err_msg=f"Jr at {regime}",
        )
    for sigma, theta, coefficients in zip(grid_sigma, grid_theta, out["w"]):
        growth = _WEIGHTS * np.exp(sigma * _TAU)
        integrand_b = _TAU * np.sinc(_TAU * theta / np.pi)  # sin(τθ)/θ
        integrand_c = _TAU**2 * 0.5 * np.sinc(_TAU * theta / (2 * np.pi)) ** 2  # (1 - cos τθ)/θ²
        expected = (np.sum(growth), np.sum(growth * integrand_b), np.sum(growth * integrand_c))
        np.testing.assert_allclose(
            coefficients,
            expected,
            rtol=1e-13,
            atol=1e-15 * np.exp(max(sigma, 0.0)),  # the integrands' scale (B, C oscillate to ~0)
            err_msg=f"W coefficients at σ={sigma}, θ={theta}",
        )


def test_sim3_second_order_and_raw_parameters():
    """Gradients and Hessians of a scalar in tangent coordinates are finite at the identity (σ and θ
    exactly 0) and the Hessian matches finite differences of the gradient (second derivatives go
    through the rules); derivatives with respect to raw parameters (`Sim3(params)`) match finite
    differences along the parameter manifold (unit quaternion)."""
    p = jnp.array([0.3, -1.2, 0.8])
    step = 1e-5

    def cost(delta, x):  # through exp's rule (J_r), compose's and act's
        return jnp.sum(x.rplus(delta).act(p) ** 2)

    @jax.jit
    def evaluate(x):
        zero = jnp.zeros(7, dtype=jnp.float64)
        gradient = jax.grad(cost)
        shifts = step * jnp.concatenate([jnp.eye(7), -jnp.eye(7)])
        around = jax.vmap(lambda d: gradient(d, x))(shifts)
        return (
            gradient(zero, x),
            jax.hessian(cost)(zero, x),
            (around[:7] - around[7:]).T / (2 * step),
        )

    for xi in (np.zeros(7), regime_tangent("random")):
        gradient, hessian, fd = (np.asarray(a) for a in evaluate(Sim3.exp(jnp.asarray(xi))))
        assert np.all(np.isfinite(gradient)) and np.all(np.isfinite(hessian))
        np.testing.assert_allclose(hessian, fd, atol=1e-6 * max(1.0, np.abs(fd).max()))

    def on_raw(params):
        return Sim3(params).normalize() @ p

    @jax.jit
    def raw(params):
        shifts = 1e-6 * jnp.concatenate([jnp.eye(8), -jnp.eye(8)])
        around = jax.vmap(lambda d: on_raw(params + d))(shifts)
        return (
            jax.jacfwd(on_raw)(params),
            jax.jacrev(on_raw)(params),
            (around[:8] - around[8:]).T / 2e-6,
        )

    params = Sim3.exp(jnp.asarray(regime_tangent("random"))).parameters()
    jac_fwd, jac_rev, fd = raw(params)
    np.testing.assert_allclose(jac_fwd, fd, atol=1e-8)
    np.testing.assert_allclose(jac_rev, jac_fwd, atol=1e-12)


def test_sim3_constructors_and_broadcasting():
    cloud = np.random.default_rng(0).normal(size=(5, 3))

    @jax.jit
    def evaluate(omega, t, scale, cloud):
        rotation = SO3.exp(omega)
        x = Sim3.from_rotation_translation_scale(rotation, t, scale)
        se3 = lieax.SE3.from_rotation_and_translation(rotation, t)
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


def test_sim3_float32():
    """float32 Exp within 1e-4 of float64 over the regimes (entries up to ~10), Log within 1e-3 (the
    float32 Jacobians are covered by the registry's float32 tests)."""
    xis = np.stack([regime_tangent(r) for r in REGIMES if r not in ("near_pi", "random_large")])

    @jax.jit
    def evaluate(xis64, xis32):
        x32 = Sim3.exp(xis32)
        return Sim3.exp(xis64).as_matrix(), x32.as_matrix(), x32.log()

    m64, m32, logs = evaluate(jnp.asarray(xis), jnp.asarray(xis, jnp.float32))
    assert m32.dtype == jnp.float32 and logs.dtype == jnp.float32
    np.testing.assert_allclose(m32, m64, atol=1e-4)
    np.testing.assert_allclose(logs, xis, atol=1e-3)


# ---- S2 ------------------------------------------------------------------------------------------

DIRECTIONS = np.array(
    [
        [0.0, 0.0, 1.0],
        [0.0, 0.0, -1.0],
        [1.0, 0.0, 0.0],
        [0.0, -1.0, 0.0],
        [0.3, -0.5, 0.81],
        [-0.6, 0.2, -0.7],
        [1.0, 1.0, 1.0],
        [-1.0, -1.0, -1.0],
        [0.2, 0.4, 0.6000001],  # near r = (1, 2, 3)/√14, where the basis is the reference frame
        list(
            np.asarray(SINGULAR_DIRECTION) + np.array([1e-2, -2e-2, 0.0])
        ),  # ~0.02 from the singular point
    ]
)
DIRECTIONS = DIRECTIONS / np.linalg.norm(DIRECTIONS, axis=1, keepdims=True)


_R = np.array([1.0, 2.0, 3.0]) / np.sqrt(14.0)
_U1 = np.array([-2.0, 1.0, 0.0]) / np.sqrt(5.0)
_U = np.stack([_U1, np.cross(_R, _U1)], axis=1)


def s2_basis_np(p):
    """The documented basis, written independently: the minimal rotation taking r to p applied to
    the reference frame, $R = I + [k]_\\times + [k]_\\times^2 / (1 + r^\\top p)$, $k = r \\times p$."""
    p = p / np.linalg.norm(p)
    k = skew(np.cross(_R, p))
    return (np.eye(3) + k + k @ k / (1.0 + _R @ p)) @ _U


def s2_plus(p, xi):
    u = p + s2_basis_np(p) @ xi
    return u / np.linalg.norm(u)


def s2_minus(q, p):
    return s2_basis_np(p).T @ q / (p @ q)


def test_s2_basis_and_retraction():
    """The basis: the documented formula, orthonormal, tangent, smooth away from the singular
    point, finite there; the retraction round trip; agreement with the exponential map to third
    order; zero error at coincident directions."""
    rng = np.random.default_rng(5)
    xi = rng.normal(size=(len(DIRECTIONS), 2))

    @jax.jit
    def evaluate(ps, xi, singular):
        p = S2(ps)
        q = p.rplus(xi)
        small = p.rplus(1e-3 * xi)
        return {
            "basis": p.basis(),
            "q": q.unit_vector(),
            "back": q.rminus(p),
            "again": p.rplus(q.rminus(p)).unit_vector(),
            "same": p.rplus(jnp.zeros_like(xi)).unit_vector(),
            "small_angle": p.distance(small),
            "self_error": p.error(p),
            "singular": S2(singular).basis(),
            "singular_gradient": jax.grad(lambda v: jnp.sum(S2(v).basis() ** 2))(singular),
            "from_vector": S2.from_vector(jnp.array([0.0, 3.0, 4.0])).unit_vector(),
        }

    out = jax.tree_util.tree_map(
        np.asarray,
        evaluate(jnp.asarray(DIRECTIONS), jnp.asarray(xi), jnp.asarray(SINGULAR_DIRECTION)),
    )
    b = out["basis"]
    for direction, basis in zip(DIRECTIONS, b):
        np.testing.assert_allclose(basis, s2_basis_np(direction), atol=1e-14)
    np.testing.assert_allclose(
        np.swapaxes(b, -1, -2) @ b, np.broadcast_to(np.eye(2), (len(b), 2, 2)), atol=1e-14
    )
    np.testing.assert_allclose(np.einsum("nij,ni->nj", b, DIRECTIONS), 0.0, atol=1e-14)
    for direction in DIRECTIONS[:-1]:
        for step in (np.array([1e-6, 0.0]), np.array([0.0, -1e-6])):
            assert (
                np.max(np.abs(s2_basis_np(s2_plus(direction, step)) - s2_basis_np(direction)))
                < 1e-4
            )
    assert np.all(np.isfinite(out["singular"])) and np.all(np.isfinite(out["singular_gradient"]))
    np.testing.assert_allclose(out["singular"].T @ out["singular"], np.eye(2), atol=1e-14)
    np.testing.assert_allclose(out["singular"].T @ np.asarray(SINGULAR_DIRECTION), 0.0, atol=1e-14)
    np.testing.assert_allclose(np.linalg.norm(out["q"], axis=-1), 1.0, atol=1e-15)
    np.testing.assert_allclose(out["back"], xi, atol=1e-12)
    np.testing.assert_allclose(out["again"], out["q"], atol=1e-14)
    np.testing.assert_allclose(out["same"], DIRECTIONS, atol=1e-16)
    np.testing.assert_allclose(
        out["small_angle"], np.arctan(np.linalg.norm(1e-3 * xi, axis=-1)), atol=1e-15
    )
    np.testing.assert_allclose(out["self_error"], 0.0, atol=1e-14)
    np.testing.assert_allclose(out["from_vector"], [0.0, 0.6, 0.8], atol=1e-16)


def _s2_fd(f, args, kinds, output, step=1e-6):
    """Central differences in local coordinates: S2 arguments moved by the retraction, SO3 by
    `R·Exp`, arrays by addition; S2 outputs compared by `⊖` at the base value."""
    base = f(*args)
    blocks = []
    for i, kind in enumerate(kinds):
        size = {"s2": 2, "so3": 3}.get(kind, np.size(args[i]))
        columns = []
        for e in np.eye(size):
            sides = []
            for sign in (1.0, -1.0):
                moved = list(args)
                if kind == "s2":
                    moved[i] = s2_plus(args[i], sign * step * e)
                elif kind == "so3":
                    moved[i] = args[i] @ scipy.linalg.expm(skew(sign * step * e))
                else:
                    moved[i] = args[i] + sign * step * e
                value = f(*moved)
                sides.append(s2_minus(value, base) if output == "s2" else np.ravel(value - base))
            columns.append((sides[0] - sides[1]) / (2 * step))
        blocks.append(np.stack(columns, axis=1))
    return blocks


@needs_manifold_patch
def test_s2_jacobians():
    """lieax.jacobian (fwd and rev, batched and one element) of rplus, rminus, rotate, error and
    distance against finite differences; rotate against the notes' closed form
    $[-B_{Rp}^\\top R[p]_\\times, B_{Rp}^\\top R B_p]$ and error's $\\partial/\\partial q = B_p^\\top B_q$."""
    rng = np.random.default_rng(11)
    count = len(DIRECTIONS)
    ps = DIRECTIONS
    qs = np.stack([s2_plus(p, 0.4 * rng.normal(size=2)) for p in ps])
    xis = 0.7 * rng.normal(size=(count, 2))
    rotations = np.stack([scipy.linalg.expm(skew(w)) for w in rng.normal(size=(count, 3))])
    rotation_params = SO3.from_matrix(jnp.asarray(rotations))
    cases = {
        "rplus": (
            lambda p, xi: p.rplus(xi),
            (S2(jnp.asarray(ps)), jnp.asarray(xis)),
            lambda p, xi: s2_plus(p, xi),
            (ps, xis),
            ("s2", "vec"),
            "s2",
        ),
        "rminus": (
            lambda q, p: q.rminus(p),
            (S2(jnp.asarray(qs)), S2(jnp.asarray(ps))),
            s2_minus,
            (qs, ps),
            ("s2", "s2"),
            "vec",
        ),
        "rotate": (
            lambda r, p: p.rotate(r),
            (rotation_params, S2(jnp.asarray(ps))),
            lambda r, p: r @ p,
            (rotations, ps),
            ("so3", "s2"),
            "s2",
        ),
        "error": (
            lambda p, q: p.error(q),
            (S2(jnp.asarray(ps)), S2(jnp.asarray(qs))),
            lambda p, q: s2_basis_np(p).T @ q,
            (ps, qs),
            ("s2", "s2"),
            "vec",
        ),
        "distance": (
            lambda p, q: p.distance(q),
            (S2(jnp.asarray(ps)), S2(jnp.asarray(qs))),
            lambda p, q: np.arctan2(np.linalg.norm(np.cross(p, q)), p @ q),
            (ps, qs),
            ("s2", "s2"),
            "vec",
        ),
    }
    out_sizes = {"rplus": 2, "rminus": 2, "rotate": 2, "error": 2, "distance": 1}

    def evaluate(all_args):
        out = {  # reverse mode where the S2 carrier maps are transposed on both sides
            name: (
                lieax.jacobian(case[0], (0, 1), mode="fwd")(*all_args[name]),
                lieax.jacobian(case[0], (0, 1), mode="rev")(*all_args[name])
                if name in ("rotate", "rminus")
                else None,
            )
            for name, case in cases.items()
        }
        p = all_args["error"][0]
        out["at_zero"] = lieax.jacobian(lambda xi, p: p.rplus(xi))(jnp.zeros((count, 2)), p)
        out["coincident"] = (
            lieax.jacobian(lambda a: a.distance(p))(p),
            lieax.jacobian(lambda a: jnp.sum(a.error(p)))(p),
        )
        rotation, direction = all_args["rotate"][0][4], all_args["rotate"][1][4]
        out["single"] = lieax.jacobian(cases["rotate"][0], (0, 1))(rotation, direction)
        return out

    jacobians = jax.jit(evaluate)({name: case[1] for name, case in cases.items()})
    for name, (f, args, reference, np_args, kinds, output) in cases.items():
        fwd, rev = jacobians[name]
        for position in range(2):
            if rev is not None:
                np.testing.assert_allclose(rev[position], fwd[position], atol=1e-12, err_msg=name)
            blocks, off = split_batched(fwd[position], count, out_sizes[name])
            assert off == 0.0, name
            for index in range(count):
                element = [a[index] for a in np_args]
                expected = _s2_fd(reference, element, kinds, output)[position]
                error = np.max(np.abs(blocks[index] - expected))
                assert error < 1e-7 * max(1.0, np.abs(expected).max()), (
                    f"S2 {name} d/d(arg {position}) at {ps[index]}: {error:.3g}\n{blocks[index]}\n{expected}"
                )
        if name == "rotate":
            for index in range(count):
                r, p = rotations[index], ps[index]
                b_out, b_in = s2_basis_np(r @ p), s2_basis_np(p)
                closed = (-b_out.T @ r @ skew(p), b_out.T @ r @ b_in)
                for position in range(2):
                    blocks, _ = split_batched(fwd[position], count, 2)
                    np.testing.assert_allclose(blocks[index], closed[position], atol=1e-14)
        if name == "error":
            blocks, _ = split_batched(fwd[1], count, 2)
            for index in range(count):
                np.testing.assert_allclose(
                    blocks[index], s2_basis_np(ps[index]).T @ s2_basis_np(qs[index]), atol=1e-14
                )
    # one element without batch axes gives the same block
    for position in range(2):
        np.testing.assert_allclose(
            jacobians["single"][position],
            split_batched(jacobians["rotate"][0][position], count, 2)[0][4],
            atol=1e-14,
        )
    # the derivative of the retraction at 0 is the identity in local coordinates
    np.testing.assert_allclose(
        split_batched(jacobians["at_zero"], count, 2)[0],
        np.broadcast_to(np.eye(2), (count, 2, 2)),
        atol=1e-14,
    )
    # NaN-free at coincident directions
    for jac in jacobians["coincident"]:
        assert np.all(np.isfinite(jac))


@needs_manifold_patch
def test_s2_in_solver_and_tree_helpers():
    """Estimate an unknown direction from rotated observations with the Levenberg-Marquardt solver,
    with the state a pytree mixing S2 and an array."""
    rng = np.random.default_rng(3)
    truth = np.array([0.2, -0.6, 0.77])
    truth /= np.linalg.norm(truth)
    rotations = SO3.exp(jnp.asarray(rng.normal(size=(20, 3))))
    observed = S2(rotations.act(jnp.asarray(truth)))
    offset_truth = jnp.array([0.5, -1.0])

    def residual(state, data):
        direction, offset = state
        rotations, observed = data
        predicted = direction.rotate(rotations)
        return observed.error(predicted), offset - offset_truth

    x0 = (S2.from_vector(jnp.array([0.0, 0.0, 1.0])), jnp.zeros(2))
    solution = lieax.lstsq.least_squares(residual, x0, (rotations, observed))
    direction, offset = solution.value
    np.testing.assert_allclose(direction.unit_vector(), truth, atol=1e-9)
    np.testing.assert_allclose(offset, offset_truth, atol=1e-9)
    assert lieax.tangent_dim(x0) == 4
    moved = lieax.rplus(x0, (jnp.array([0.1, 0.2]), jnp.ones(2)))
    np.testing.assert_allclose(lieax.rminus(moved, x0)[0], [0.1, 0.2], atol=1e-14)
    gradient = lieax.grad(lambda s: jnp.sum(s.unit_vector() * jnp.array([1.0, 2.0, 3.0])))(x0[0])
    assert gradient.shape == (2,)
