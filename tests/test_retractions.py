"""`lieax.retractions`: Cayley and first-order retractions against their matrix formulas, their
agreement with Exp (first order, with the measured order of the difference), derivatives (identity
at zero; the closed-form rules of the Cayley kernels against finite differences; forward vs
reverse; NaN-free gradients and Hessians at zero), round trips with the inverses, batching, the
fallback to Exp, and their use in `lieax.rplus`, `least_squares` (also under `vmap` and with
unrolled differentiation) and `lieax.optax`.

Each (retraction, group) case is evaluated by one jitted call (`results`), cached; the tests
compare its outputs in NumPy.
"""

import functools

import jax
import jax.numpy as jnp
import numpy as np
import optax
import pytest
import scipy.linalg
from registry import skew3

import lieax
import lieax.lstsq as ls
import lieax.optax
from lieax import retractions

SO3, SE3 = lieax.SO3, lieax.SE3
CASES = [("cayley", SO3), ("cayley", SE3), ("first_order", SE3)]
CASE_IDS = [f"{name}-{G.__name__}" for name, G in CASES]
STEPS = np.array([1e-2, 1e-3, 1e-4])  # t in the first-order agreement test
# the order p of |R_X(tδ) ⊖ X Exp(tδ)| = O(t^p): Cayley's rotation angle is 2 atan(θ/2) = θ - θ³/12
# + ..., about the same axis (third order); the SE3 retractions' translation t + R v misses
# R (W(ω) - I) v = R (ω × v) / 2 + ... (second order)
ORDER = {"cayley-SO3": 3, "cayley-SE3": 2, "first_order-SE3": 2}
FD_EPS = 1e-6
COUNT = 6  # elements in the batch


def tangents(G, count, seed, angle=(0.2, 2.8)):
    """Tangents with rotation angles uniform in `angle` and normal translations."""
    rng = np.random.default_rng(seed)
    omega = rng.normal(size=(count, 3))
    omega *= rng.uniform(*angle, size=(count, 1)) / np.linalg.norm(omega, axis=1, keepdims=True)
    if G is SO3:
        return omega
    return np.concatenate([rng.normal(size=(count, 3)), omega], axis=1)


# ---- NumPy references -----------------------------------------------------------------------------


def cayley_matrix(omega):
    r"""$(I - \tfrac12 K)^{-1}(I + \tfrac12 K)$, $K = [\omega]_\times$ (GTSAM math notes 12.4)."""
    k = skew3(omega)
    return np.linalg.solve(np.eye(3) - 0.5 * k, np.eye(3) + 0.5 * k)


def reference_rplus(name, G, x, delta):
    """The retraction on matrices: SO3 `R C(ω)`; SE3 `(R Q(ω), t + R v)`, Q Cayley or `expm`."""
    omega = delta[-3:]
    rotation = cayley_matrix(omega) if name == "cayley" else scipy.linalg.expm(skew3(omega))
    if G is SO3:
        return x @ rotation
    increment = np.eye(4)
    increment[:3, :3], increment[:3, 3] = rotation, delta[:3]
    return x @ increment


# ---- one jitted evaluation per case ----------------------------------------------------------------


@functools.cache
def results(name, G):
    retraction = getattr(retractions, name)
    dim = G.tangent_dim
    xs = G.exp(jnp.asarray(tangents(G, COUNT, seed=1)))
    deltas = jnp.asarray(tangents(G, COUNT, seed=2, angle=(0.1, 2.0)))
    ys = G.exp(jnp.asarray(tangents(G, COUNT, seed=3)))
    direction = jnp.asarray(tangents(G, 1, seed=4, angle=(1.0, 1.0))[0])
    eye = jnp.eye(dim)

    def rplus(x, delta):
        return retraction.rplus(x, delta)

    def rminus(y, x):
        return retraction.rminus(y, x)

    shifts = FD_EPS * jnp.concatenate([eye, -eye])  # ± in one vmap: one copy of each program

    def central(moved):
        """`(moved(εe_k) - moved(-εe_k)) / 2ε` as column k."""
        plus, minus = jnp.split(jax.vmap(moved)(shifts), 2)
        return ((plus - minus) / (2 * FD_EPS)).T

    def fd(f, at):
        """Central differences of `f` at `at` (a tangent), read out by `⊖ f(at)` (Exp's)."""
        base = f(at)
        return central(lambda d: f(at + d).rminus(base))

    def fd_rminus(y, x):
        """Central differences of `rminus(y, x)` with respect to `y` (moved by Exp)."""
        return central(lambda d: rminus(y.rplus(d), x))

    def f(x):
        """A smooth scalar function of a point."""
        return jnp.sum(jnp.sin(x.as_matrix())) + jnp.sum(x @ jnp.array([0.3, -1.2, 0.8]))

    def scalar(delta, x):
        """`f` of the retracted point, for gradients and Hessians."""
        return f(rplus(x, delta))

    def scalar_exp(delta, x):
        return f(x.rplus(delta))

    def evaluate(xs, deltas, ys, direction):
        x0 = xs[0]
        zero = jnp.zeros(dim)
        single = jax.vmap(rplus)  # the unbatched function, vmapped
        # calls of the same function share one call on stacked cases where their inputs allow
        # it (one copy of the kernel in the program; the same values)
        stack = lambda *elements: jax.tree_util.tree_map(lambda *u: jnp.stack(u), *elements)
        retracted = rplus(xs, deltas)
        differences = rminus(ys, xs)
        round_trip_tangent, rminus_self = rminus(stack(retracted, xs), stack(xs, xs))
        steps = jnp.asarray(STEPS)[:, None] * direction
        # finite differences in δ at each (X, δ) and at (X0, 0); gradients at δ = 0 for every X
        # and the identity; Hessians at those and at each (X, δ): one vmapped call each
        join = lambda *batches: jax.tree_util.tree_map(lambda *u: jnp.concatenate(u), *batches)
        one = lambda element: jax.tree_util.tree_map(lambda u: u[None], element)
        fd_delta_and_zero = jax.vmap(lambda x, d: fd(lambda e: rplus(x, e), d))(
            join(xs, one(x0)), jnp.concatenate([deltas, zero[None]])
        )
        at_zero = join(xs, one(G.identity()))
        grads = jax.vmap(jax.grad(scalar))(jnp.zeros((COUNT + 1, dim)), at_zero)
        hessians = jax.vmap(jax.hessian(scalar))(
            jnp.concatenate([jnp.zeros((COUNT + 1, dim)), deltas]), join(at_zero, xs)
        )
        out = {
            "x": xs.as_matrix(),
            "y": ys.as_matrix(),
            "retracted": retracted.as_matrix(),
            "retracted_vmapped": single(xs, deltas).as_matrix(),
            "retracted_broadcast": rplus(x0, deltas).as_matrix(),  # one X, a batch of δ
            "round_trip_tangent": round_trip_tangent,
            "round_trip_point": rplus(xs, differences).as_matrix(),
            "rminus_vmapped": jax.vmap(rminus)(ys, xs),
            "rminus": differences,
            "rminus_self": rminus_self,
            # |R_X(tδ) ⊖ X Exp(tδ)| for the steps t
            "agreement": jnp.linalg.norm(rplus(x0, steps).rminus(x0.rplus(steps)), axis=-1),
            # derivatives at δ = 0: the identity
            "jacobian_zero_fwd": lieax.jacobian(rplus, 1, mode="fwd")(x0, zero),
            "jacobian_zero_rev": lieax.jacobian(rplus, 1, mode="rev")(x0, zero),
            "fd_zero": fd_delta_and_zero[-1],
            "rminus_jacobian_zero": lieax.jacobian(rminus, 0)(x0, x0),
            # the kernels' rules at δ ≠ 0, against finite differences
            "jacobian": jax.vmap(lieax.jacobian(rplus, (0, 1)))(xs, deltas),
            "fd_delta": fd_delta_and_zero[:-1],
            "fd_x": jax.vmap(lambda x, d: fd(lambda e: rplus(x.rplus(e), d), zero))(xs, deltas),
            "rminus_jacobian": jax.vmap(lieax.jacobian(rminus, (0, 1), mode="rev"))(ys, xs),
            "fd_rminus_y": jax.vmap(fd_rminus)(ys, xs),
            "fd_rminus_x": jax.vmap(lambda y, x: central(lambda d: rminus(y, x.rplus(d))))(ys, xs),
            # raw-parameter derivatives: forward and reverse mode agree (the rules transpose)
            "jacfwd_raw": jax.jacfwd(lambda p, d: rplus(G(p), d).parameters(), (0, 1))(
                x0.parameters(), deltas[0]
            ),
            "jacrev_raw": jax.jacrev(lambda p, d: rplus(G(p), d).parameters(), (0, 1))(
                x0.parameters(), deltas[0]
            ),
            # gradients and Hessians at δ = 0 (also at the identity), and at δ ≠ 0
            "grad_zero": grads[:COUNT],
            "hessian_zero": hessians[:COUNT],
            "grad_identity": grads[COUNT],
            "hessian_identity": hessians[COUNT],
            "local_grad": jax.vmap(lieax.grad(f))(xs),
            "grad_exp": jax.vmap(jax.grad(scalar_exp), (None, 0))(zero, xs),
            "hessian_delta": hessians[COUNT + 1 :],
            "rminus_grad_self": jax.grad(lambda p: jnp.sum(rminus(G(p), x0)))(x0.parameters()),
        }
        return out

    out = jax.jit(evaluate)(xs, deltas, ys, direction)
    inputs = {
        "deltas": np.asarray(deltas),
        "direction": np.asarray(direction),
    }
    return jax.tree_util.tree_map(np.asarray, out), inputs


@pytest.mark.parametrize("name, G", CASES, ids=CASE_IDS)
def test_values_match_the_matrix_formulas(name, G):
    """`R·C(ω)` (GTSAM's Cayley retraction), `(R·Q(ω), t + R v)`; batched == vmapped; one element
    broadcasts against a batch of tangents."""
    out, inputs = results(name, G)
    expected = np.stack(
        [reference_rplus(name, G, x, d) for x, d in zip(out["x"], inputs["deltas"])]
    )
    np.testing.assert_allclose(out["retracted"], expected, rtol=0, atol=1e-13)
    np.testing.assert_allclose(out["retracted_vmapped"], out["retracted"], rtol=0, atol=1e-15)
    broadcast = np.stack([reference_rplus(name, G, out["x"][0], d) for d in inputs["deltas"]])
    np.testing.assert_allclose(out["retracted_broadcast"], broadcast, rtol=0, atol=1e-13)


def test_cayley_matches_gtsam_closed_form():
    """GTSAM's `Rot3::CayleyChart::Retract`, written out: entries `(4 + x² - y² - z²) f`,
    `(xy - 2z) 2f`, ... with `f = 1 / (4 + |ω|²)` (the Cayley transform of `-[ω]×/2`)."""
    omega = np.array([0.3, -1.1, 2.4])
    x, y, z = omega
    f = 1.0 / (4.0 + omega @ omega)
    gtsam = np.array(
        [
            [(4 + x * x - y * y - z * z) * f, (x * y - 2 * z) * 2 * f, (x * z + 2 * y) * 2 * f],
            [(x * y + 2 * z) * 2 * f, (4 - x * x + y * y - z * z) * f, (y * z - 2 * x) * 2 * f],
            [(x * z - 2 * y) * 2 * f, (y * z + 2 * x) * 2 * f, (4 - x * x - y * y + z * z) * f],
        ]
    )
    moved = retractions.cayley.rplus(SO3.identity(), jnp.asarray(omega))
    np.testing.assert_allclose(moved.as_matrix(), gtsam, atol=1e-15)
    np.testing.assert_allclose(gtsam, cayley_matrix(omega), atol=1e-15)
    # rotation angle 2 atan(|ω| / 2) about ω
    np.testing.assert_allclose(
        moved.log(), 2 * np.arctan(np.linalg.norm(omega) / 2) * omega / np.linalg.norm(omega)
    )


@pytest.mark.parametrize("name, G", CASES, ids=CASE_IDS)
def test_agrees_with_exp_to_first_order(name, G):
    """`|R_X(tδ) ⊖ X Exp(tδ)| = O(t^p)` with p >= 2: the ratio to t^p settles as t shrinks (each
    tenfold step shrinks the difference 10^p-fold), and is not trivially zero."""
    out, _ = results(name, G)
    errors, order = out["agreement"], ORDER[f"{name}-{G.__name__}"]
    assert np.all(errors > 0)
    observed = np.log10(errors[:-1] / errors[1:])  # per tenfold step of t
    np.testing.assert_allclose(observed, order, atol=0.05, err_msg=f"orders {observed}")
    ratios = errors / STEPS**order
    np.testing.assert_allclose(ratios[1:], ratios[-1], rtol=0.05)
    assert errors[-1] < 1e-7  # t = 1e-4


@pytest.mark.parametrize("name, G", CASES, ids=CASE_IDS)
def test_derivative_at_zero_is_the_identity(name, G):
    out, _ = results(name, G)
    eye = np.eye(G.tangent_dim)
    for key in ("jacobian_zero_fwd", "jacobian_zero_rev", "rminus_jacobian_zero"):
        np.testing.assert_allclose(out[key], eye, rtol=0, atol=1e-14, err_msg=key)
    np.testing.assert_allclose(out["fd_zero"], eye, rtol=0, atol=1e-8)
    # so gradients in tangent coordinates are the same as with Exp (and as `lieax.grad`)
    np.testing.assert_allclose(out["grad_zero"], out["grad_exp"], rtol=0, atol=1e-13)
    np.testing.assert_allclose(out["local_grad"], out["grad_exp"], rtol=0, atol=1e-13)


@pytest.mark.parametrize("name, G", CASES, ids=CASE_IDS)
def test_jacobians_match_finite_differences(name, G):
    """The closed-form rules (Cayley's `4/(4 + θ²) (I - [ω]×/2)` and its inverse
    `I + [ω]×/2 + ωωᵀ/4`) away from zero, with respect to the point and the tangent, for the
    retraction and its inverse; forward and reverse mode on raw parameters agree."""
    out, _ = results(name, G)
    jac_x, jac_delta = out["jacobian"]
    np.testing.assert_allclose(jac_delta, out["fd_delta"], atol=1e-7)
    np.testing.assert_allclose(jac_x, out["fd_x"], atol=1e-7)
    jac_y, jac_x_inverse = out["rminus_jacobian"]
    np.testing.assert_allclose(jac_y, out["fd_rminus_y"], atol=1e-7 * max(1, np.abs(jac_y).max()))
    np.testing.assert_allclose(
        jac_x_inverse, out["fd_rminus_x"], atol=1e-7 * max(1, np.abs(jac_x_inverse).max())
    )
    for fwd, rev in zip(out["jacfwd_raw"], out["jacrev_raw"]):
        assert np.all(np.isfinite(fwd))
        np.testing.assert_allclose(rev, fwd, atol=1e-13)


@pytest.mark.parametrize("name, G", CASES, ids=CASE_IDS)
def test_gradients_are_finite(name, G):
    """`jax.grad` and `jax.hessian` through the retraction at δ = 0 (at the identity too), at
    δ ≠ 0, and through the inverse at `Y = X`: finite."""
    out, _ = results(name, G)
    for key in (
        "grad_zero",
        "hessian_zero",
        "grad_identity",
        "hessian_identity",
        "hessian_delta",
        "rminus_grad_self",
    ):
        assert np.all(np.isfinite(out[key])), key


@pytest.mark.parametrize("name, G", CASES, ids=CASE_IDS)
def test_round_trips_with_the_inverse(name, G):
    """`rminus(rplus(X, δ), X) = δ`, `rplus(X, rminus(Y, X)) = Y`, `rminus(X, X) = 0`; batched ==
    vmapped."""
    out, inputs = results(name, G)
    np.testing.assert_allclose(out["round_trip_tangent"], inputs["deltas"], atol=1e-12)
    np.testing.assert_allclose(out["round_trip_point"], out["y"], atol=1e-12)
    np.testing.assert_allclose(out["rminus_self"], 0.0, atol=1e-15)
    np.testing.assert_allclose(out["rminus_vmapped"], out["rminus"], rtol=0, atol=1e-14)


def test_fallbacks_and_the_exp_retraction():
    """Groups and arrays without a rule move by Exp (`first_order` on SO3 is Exp: its rotation is
    exact); `exp` is `X.rplus` / `X.rminus`; `lieax.rplus` / `rminus` apply a retraction to a
    pytree leaf by leaf; float32 stays float32."""
    rng = np.random.default_rng(5)
    tree = {
        "so2": lieax.SO2.exp(jnp.asarray(rng.normal(size=(2, 1)))),
        "se2": lieax.SE2.exp(jnp.asarray(rng.normal(size=3))),
        "sim3": lieax.Sim3.exp(jnp.asarray(0.5 * rng.normal(size=7))),
        "s2": lieax.S2(jnp.asarray([0.3, -0.5, 0.81]) / np.sqrt(0.9961)),
        "array": jnp.asarray(rng.normal(size=(2, 3))),
    }
    delta = jax.tree_util.tree_map(
        lambda t: jnp.asarray(0.3 * rng.normal(size=t.shape)), lieax.zero_tangents(tree)
    )
    expected = lieax.rplus(tree, delta)
    for retraction in (retractions.exp, retractions.cayley, retractions.first_order):
        moved = lieax.rplus(tree, delta, retraction=retraction)
        for a, b in zip(jax.tree_util.tree_leaves(moved), jax.tree_util.tree_leaves(expected)):
            np.testing.assert_array_equal(a, b)
        back = lieax.rminus(moved, tree, retraction=retraction)
        for a, b in zip(jax.tree_util.tree_leaves(back), jax.tree_util.tree_leaves(delta)):
            np.testing.assert_allclose(a, b, atol=1e-12)
    rotation = SO3.exp(jnp.array([0.3, -0.2, 1.0]))
    omega = jnp.array([0.5, 0.1, -0.7])
    np.testing.assert_array_equal(
        retractions.first_order.rplus(rotation, omega).parameters(),
        rotation.rplus(omega).parameters(),
    )
    # SO3 and SE3 leaves of a pytree take the retraction's own rule
    poses = {"r": rotation, "t": SE3.exp(jnp.arange(6.0) / 10)}
    steps = {"r": omega, "t": jnp.array([0.1, 0.2, 0.3, 0.4, -0.5, 0.6])}
    moved = lieax.rplus(poses, steps, retractions.cayley)
    np.testing.assert_allclose(
        moved["r"].as_matrix(), rotation.as_matrix() @ cayley_matrix(np.asarray(omega)), atol=1e-15
    )
    np.testing.assert_allclose(
        lieax.rminus(moved, poses, retractions.cayley)["t"], steps["t"], atol=1e-14
    )
    single = SE3.identity(dtype=jnp.float32)
    for retraction in (retractions.cayley, retractions.first_order):
        moved = retraction.rplus(single, jnp.ones(6, jnp.float32))
        assert moved.parameters().dtype == jnp.float32
        assert retraction.rminus(moved, single).dtype == jnp.float32
    assert repr(retractions.cayley) == "lieax.retractions.cayley"


def test_bad_arguments():
    with pytest.raises(TypeError, match="lieax.retractions.Retraction"):
        lieax.rplus(SO3.identity(), jnp.zeros(3), retraction="cayley")
    with pytest.raises(TypeError, match="lieax.retractions.Retraction"):
        ls.least_squares(lambda x, a: x.log(), SO3.identity(), retraction=retractions.cayley.rplus)
    with pytest.raises(ValueError, match=r"\(\*batch, 6\)"):
        retractions.cayley.rplus(SE3.identity(), jnp.zeros(3))
    with pytest.raises(TypeError, match="SE3"):
        retractions.cayley.rminus(SE3.identity(), SO3.identity())


# ---- solvers ---------------------------------------------------------------------------------------


def kabsch(source, target):
    """The rotation and translation minimizing `sum |R p + t - q|²` (SVD, proper rotation)."""
    mu_p, mu_q = source.mean(0), target.mean(0)
    u, _, vt = np.linalg.svd((target - mu_q).T @ (source - mu_p))
    d = np.diag([1.0, 1.0, np.sign(np.linalg.det(u @ vt))])
    rotation = u @ d @ vt
    return rotation, mu_q - rotation @ mu_p


def alignment_data(key, count=5, n=30):
    """`count` point-set pairs, each related by a rotation of 1-2.5 rad and a translation, with
    noise (so residuals do not vanish at the optimum)."""
    k1, k2 = jax.random.split(key)
    source = jax.random.normal(k1, (count, n, 3))
    xi = jnp.asarray(tangents(SE3, count, seed=11, angle=(1.0, 2.5)))
    target = jax.vmap(lambda T, p: T @ p)(SE3.exp(xi), source)
    return source, target + 0.05 * jax.random.normal(k2, target.shape)


def se3_residual(pose, data):
    source, target = data
    return jax.vmap(lambda p, q: pose @ p - q)(source, target)


def split_residual(x, data):
    source, target = data
    return jax.vmap(lambda p, q: x["rotation"] @ p + x["translation"] - q)(source, target)


TOLERANCES = {"function_tolerance": 0.0, "gradient_tolerance": 1e-13, "parameter_tolerance": 1e-14}
TIGHT = {"termination": ls.Termination(**TOLERANCES)}


@functools.cache
def alignment_problems():
    """`(sources, targets)` of the alignment problems (made when a test first needs them, not
    while pytest collects the file)."""
    return alignment_data(jax.random.PRNGKey(0))


def sources():
    return alignment_problems()[0]


def targets():
    return alignment_problems()[1]


RETRACTIONS = ("exp", "cayley", "first_order")


@functools.cache
def single_solves():
    """The first problem solved from the identity with each retraction (one compile each)."""
    return {
        name: ls.least_squares(
            se3_residual,
            SE3.identity(),
            (sources()[0], targets()[0]),
            retraction=getattr(retractions, name),
            **TIGHT,
        )
        for name in RETRACTIONS
    }


def test_least_squares_reaches_the_same_optimum():
    """An SE3 alignment (rotation 1-2.5 rad from the start) converges to the closed-form optimum
    with every retraction; the paths differ (Cayley's iterates are not Exp's)."""
    rotation, translation = kabsch(np.asarray(sources()[0]), np.asarray(targets()[0]))
    solutions = single_solves()
    for name, solution in solutions.items():
        assert solution.status == ls.Status.CONVERGED, name
        matrix = np.asarray(solution.value.as_matrix())
        np.testing.assert_allclose(matrix[:3, :3], rotation, atol=1e-10, err_msg=name)
        np.testing.assert_allclose(matrix[:3, 3], translation, atol=1e-10, err_msg=name)
        np.testing.assert_allclose(solution.cost, solutions["exp"].cost, rtol=1e-12)
    histories = {name: np.asarray(s.cost_history) for name, s in solutions.items()}
    assert not np.allclose(histories["cayley"], histories["exp"], rtol=1e-6, equal_nan=True)


@pytest.mark.parametrize("name", ["cayley", "first_order"])
def test_least_squares_under_vmap(name):
    """Five problems solved in one `vmap` (a pose per problem) reach each its closed-form optimum,
    and the batched solve's first problem equals the single solve."""
    solve = jax.jit(
        jax.vmap(
            lambda data: ls.least_squares(
                se3_residual,
                SE3.identity(),
                data,
                retraction=getattr(retractions, name),
                throw=False,
                **TIGHT,
            )
        )
    )
    batch = solve((sources(), targets()))
    assert np.all(np.asarray(batch.status) == ls.Status.CONVERGED)
    matrices = np.asarray(batch.value.as_matrix())
    for i in range(len(sources())):
        rotation, translation = kabsch(np.asarray(sources()[i]), np.asarray(targets()[i]))
        np.testing.assert_allclose(matrices[i, :3, :3], rotation, atol=1e-10)
        np.testing.assert_allclose(matrices[i, :3, 3], translation, atol=1e-10)
    single = single_solves()[name]
    np.testing.assert_allclose(matrices[0], single.value.as_matrix(), atol=1e-12)


def solve_split(target, retraction, differentiation):
    """A `{"rotation": SO3, "translation": array}` alignment (SO3 leaf by Cayley, the array by
    addition), the solution's rotation matrix and translation as one vector."""
    solution = ls.least_squares(
        split_residual,
        {"rotation": SO3.identity(), "translation": jnp.zeros(3)},
        (sources()[1], target),
        retraction=retraction,
        differentiation=differentiation,
        termination=ls.Termination(max_iterations=30, **TOLERANCES),
    )
    value = solution.value
    return jnp.concatenate([value["rotation"].as_matrix().ravel(), value["translation"]])


def test_unrolled_differentiation_through_a_cayley_solve():
    """Reverse mode through the unrolled Cayley iterations equals the implicit derivative (which
    is taken along Exp: at the optimum the Hessian does not depend on the retraction), and the
    solution is the closed-form one."""
    value = solve_split(targets()[1], retractions.cayley, "implicit")
    rotation, translation = kabsch(np.asarray(sources()[1]), np.asarray(targets()[1]))
    np.testing.assert_allclose(value, np.r_[rotation.ravel(), translation], atol=1e-10)
    weights = jnp.linspace(-1.0, 1.0, 12)
    unrolled = jax.grad(lambda t: solve_split(t, retractions.cayley, "unrolled") @ weights)(
        targets()[1]
    )
    implicit = jax.grad(lambda t: solve_split(t, retractions.cayley, "implicit") @ weights)(
        targets()[1]
    )
    assert np.all(np.isfinite(unrolled)) and np.abs(implicit).max() > 1e-3
    np.testing.assert_allclose(unrolled, implicit, atol=1e-8)


def alignment_loss(x, data):
    return 0.5 * jnp.sum(split_residual(x, data) ** 2)


def test_optax_with_a_retraction():
    """Adam with Cayley updates reaches the closed-form optimum; `apply_updates` applies the
    retraction."""
    start = {"rotation": SO3.identity(), "translation": jnp.zeros(3)}
    adam = optax.adam(optax.exponential_decay(0.1, transition_steps=200, decay_rate=0.5))
    result = lieax.optax.minimize(
        alignment_loss,
        start,
        adam,
        1500,
        (sources()[2], targets()[2]),
        retraction=retractions.cayley,
    )
    rotation, translation = kabsch(np.asarray(sources()[2]), np.asarray(targets()[2]))
    np.testing.assert_allclose(result.value["rotation"].as_matrix(), rotation, atol=1e-7)
    np.testing.assert_allclose(result.value["translation"], translation, atol=1e-7)
    updates = {"rotation": jnp.array([0.2, -0.4, 0.9]), "translation": jnp.ones(3)}
    moved = lieax.optax.apply_updates(start, updates, retraction=retractions.cayley)
    np.testing.assert_allclose(
        moved["rotation"].as_matrix(), cayley_matrix(np.array([0.2, -0.4, 0.9])), atol=1e-15
    )
    np.testing.assert_allclose(moved["translation"], np.ones(3))
