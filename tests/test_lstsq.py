"""Tests of lieax.lstsq: problems with known optima, robust losses, statuses, vmap, implicit
derivatives. Residual functions are defined once at module level so that every solve with the
same problem, solver and shapes reuses one compilation."""

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

jax.config.update("jax_enable_x64", True)

import lieax  # noqa: E402
import lieax.lstsq as ls  # noqa: E402

SOLVERS = {"LM": ls.LevenbergMarquardt(), "GN": ls.GaussNewton()}
TIGHT = dict(
    termination=ls.Termination(
        function_tolerance=0.0, gradient_tolerance=1e-14, parameter_tolerance=1e-15
    )
)


# ---- problems -----------------------------------------------------------------------------------


def umeyama(source, target, with_scale=True):
    r"""Closed-form minimizer of $\sum_i \|s R p_i + t - q_i\|^2$ (Umeyama 1991): `(R, t, s)`."""
    source, target = np.asarray(source), np.asarray(target)
    mu_p, mu_q = source.mean(0), target.mean(0)
    p, q = source - mu_p, target - mu_q
    u, sigma, vt = np.linalg.svd(q.T @ p / len(p))
    d = np.diag([1.0, 1.0, np.sign(np.linalg.det(u) * np.linalg.det(vt))])
    rotation = u @ d @ vt
    scale = np.trace(np.diag(sigma) @ d) / np.mean(np.sum(p**2, axis=1)) if with_scale else 1.0
    return rotation, mu_q - scale * rotation @ mu_p, scale


def similarity_residual(x, data):
    r"""A pose split into a rotation and a vector, plus a log-scale: $e^\sigma R p + t - q$."""
    source, target = data
    rotation, translation, log_scale = x["rotation"], x["translation"], x["log_scale"]
    return jax.vmap(lambda p, q: jnp.exp(log_scale) * (rotation @ p) + translation - q)(
        source, target
    )


def similarity_start(dtype=jnp.float64):
    return {
        "rotation": lieax.SO3.exp(jnp.array([0.1, -0.2, 0.3], dtype)),
        "translation": jnp.zeros(3, dtype),
        "log_scale": jnp.zeros((), dtype),
    }


def similarity_data(key, n=40, noise=0.01, dtype=jnp.float64):
    k1, k2 = jax.random.split(key)
    rotation = lieax.SO3.exp(jnp.array([0.4, -0.9, 1.2]))
    source = jax.random.normal(k1, (n, 3))
    target = 1.3 * (rotation @ source) + jnp.array([0.5, -1.0, 2.0])
    target = target + noise * jax.random.normal(k2, (n, 3))
    return source.astype(dtype), target.astype(dtype)


def check_similarity(value, data, atol):
    rotation, translation, scale = umeyama(*data)
    np.testing.assert_allclose(value["rotation"].as_matrix(), rotation, atol=atol)
    np.testing.assert_allclose(value["translation"], translation, atol=atol)
    np.testing.assert_allclose(jnp.exp(value["log_scale"]), scale, atol=atol)


def rosenbrock_residual(rotation, _):
    """Rosenbrock's valley in the exponential coordinates of a rotation; minimum at Exp(1, 1, 1)."""
    w = rotation.log()
    return jnp.stack([1 - w[0], 10 * (w[1] - w[0] ** 2), 1 - w[1], 10 * (w[2] - w[1] ** 2)])


def chain_residual(poses, data):
    r"""Relative-pose residuals $\mathrm{Log}(Z_{ij}^{-1} X_i^{-1} X_j)$ and a prior on the first
    pose."""
    first, second, measured, prior = data
    between = poses[first].between(poses[second])
    return lieax.rminus(between, measured), lieax.rminus(poses[0], prior)


@functools.partial(jax.jit, static_argnums=(0, 2))
def chain_problem(group, key, size=8):
    """A chain of `size` poses with odometry, two loop closures and a prior, all exact."""
    k1, k2 = jax.random.split(key)
    truth = group.sample_uniform(k1, (size,), dtype=jnp.float64)
    first = jnp.array([*range(size - 1), 0, 2])
    second = jnp.array([*range(1, size), size - 1, size - 2])
    measured = truth[first].between(truth[second])
    start = truth.rplus(0.2 * jax.random.normal(k2, (size, group.tangent_dim)))
    return truth, start, (first, second, measured, truth[0])


def log_residual(x, target):
    r"""$\log x - \log t$: a full Gauss-Newton step from $x = e^3$ towards $t = 1$ lands at
    $x < 0$."""
    return jnp.log(x) - jnp.log(target)


# ---- convergence on known optima ----------------------------------------------------------------


@pytest.mark.parametrize("solver", SOLVERS)
def test_mixed_pytree_alignment_matches_umeyama(solver):
    data = similarity_data(jax.random.PRNGKey(0))
    sol = ls.least_squares(similarity_residual, similarity_start(), data, solver=SOLVERS[solver])
    assert sol.status_name == "CONVERGED"
    assert isinstance(sol.value["rotation"], lieax.SO3)
    check_similarity(sol.value, data, atol=1e-8)
    history = np.asarray(sol.cost_history)
    assert history[0] > sol.cost and np.isclose(history[int(sol.iterations)], sol.cost)
    assert np.all(np.isnan(history[int(sol.iterations) + 1 :]))


@pytest.mark.parametrize("solver", SOLVERS)
def test_se3_alignment_matches_closed_form(solver):
    source, target = similarity_data(jax.random.PRNGKey(1))
    target = target / 1.3  # rigid: no scale

    def residual(pose, data):
        return jax.vmap(lambda p, q: pose @ p - q)(*data)

    start = lieax.SE3.identity(dtype=jnp.float64)
    sol = ls.least_squares(residual, start, (source, target), solver=SOLVERS[solver])
    rotation, translation, _ = umeyama(source, target, with_scale=False)
    assert sol.status_name == "CONVERGED"
    np.testing.assert_allclose(sol.value.rotation().as_matrix(), rotation, atol=1e-8)
    np.testing.assert_allclose(sol.value.translation(), translation, atol=1e-8)


@pytest.mark.parametrize("solver", SOLVERS)
def test_rosenbrock_on_so3(solver):
    start = lieax.SO3.exp(jnp.array([-1.2, 1.0, 0.5]))
    sol = ls.least_squares(rosenbrock_residual, start, None, solver=SOLVERS[solver])
    assert sol.status_name == "CONVERGED"
    np.testing.assert_allclose(sol.value.log(), [1.0, 1.0, 1.0], atol=1e-7)
    assert sol.cost < 1e-14


def test_se2_pose_chain_reaches_ground_truth():
    truth, start, data = chain_problem(lieax.SE2, jax.random.PRNGKey(2))
    sol = ls.least_squares(chain_residual, start, data)
    assert sol.status_name == "CONVERGED"
    assert sol.value.batch_shape == truth.batch_shape
    np.testing.assert_allclose(lieax.rminus(sol.value, truth), 0.0, atol=1e-8)


def test_gauss_newton_with_an_unconstrained_variable():
    r"""A variable no residual touches makes $J^\top J$ singular: the fallback keeps it in place."""
    data = similarity_data(jax.random.PRNGKey(0))
    start = {**similarity_start(), "unused": jnp.array([0.25, -0.5])}

    def residual(x, data):
        used = {k: x[k] for k in ("rotation", "translation", "log_scale")}
        return similarity_residual(used, data)

    sol = ls.least_squares(residual, start, data, solver=ls.GaussNewton())
    assert sol.status_name == "CONVERGED"
    np.testing.assert_allclose(sol.value["unused"], [0.25, -0.5], atol=1e-12)
    check_similarity(sol.value, data, atol=1e-8)


def test_float32():
    data = similarity_data(jax.random.PRNGKey(0), dtype=jnp.float32)
    sol = ls.least_squares(similarity_residual, similarity_start(jnp.float32), data)
    assert sol.status_name == "CONVERGED"
    assert sol.value["translation"].dtype == jnp.float32 and sol.cost.dtype == jnp.float32
    check_similarity(sol.value, data, atol=1e-4)


# ---- robust losses ------------------------------------------------------------------------------

LOSSES = {
    "Huber": ls.Huber(0.05),
    "Cauchy": ls.Cauchy(0.05),
    "Tukey": ls.Tukey(0.5),
    "GemanMcClure": ls.GemanMcClure(0.1),
}
# Huber bounds the influence of outliers, Cauchy and Geman-McClure make it small, Tukey removes it
# (the inliers are exact); the bounded losses are not convex and start from the Huber fit.
ROTATION_ERROR = {"Huber": 0.05, "Cauchy": 1e-3, "Tukey": 1e-9, "GemanMcClure": 1e-5}


def outlier_data():
    """40 exact pairs of which 10 targets are moved by 1 to 3 units."""
    source, target = similarity_data(jax.random.PRNGKey(3), noise=0.0)
    offsets = jax.random.uniform(jax.random.PRNGKey(4), (10, 3), minval=1.0, maxval=3.0)
    return source, target.at[::4].add(offsets)


def robust_fit(data, loss, start):
    return ls.least_squares(similarity_residual, start, data, loss=loss)


@pytest.mark.parametrize("name", LOSSES)
def test_robust_losses_reject_planted_outliers(name):
    data = outlier_data()
    rotation, translation, scale = umeyama(data[0][1::4], data[1][1::4])  # the inliers' fit
    plain = ls.least_squares(similarity_residual, similarity_start(), data)
    start = plain.value
    if name in ("Tukey", "GemanMcClure"):
        start = robust_fit(data, LOSSES["Huber"], plain.value).value
    robust = robust_fit(data, LOSSES[name], start)
    assert robust.status_name == "CONVERGED"
    error = np.abs(robust.value["rotation"].as_matrix() - rotation).max()
    assert np.abs(plain.value["rotation"].as_matrix() - rotation).max() > 0.1
    assert error < ROTATION_ERROR[name]
    if name == "Tukey":
        np.testing.assert_allclose(robust.value["translation"], translation, atol=1e-9)
        np.testing.assert_allclose(jnp.exp(robust.value["log_scale"]), scale, atol=1e-9)


@pytest.mark.parametrize("name", LOSSES)
def test_loss_values_and_weights(name):
    loss = LOSSES[name]
    s = loss.scale**2 * jnp.array([0.0, 1e-9, 0.3, 0.999, 4.0, 1e4])
    np.testing.assert_allclose(loss(s[:2]), s[:2], rtol=1e-8, atol=1e-20)  # rho(s) = s near zero
    np.testing.assert_allclose(loss.weight(s), jax.vmap(jax.grad(loss))(s), rtol=1e-10, atol=1e-14)
    assert np.all(np.diff(np.asarray(loss(s))) >= 0) and np.all(np.asarray(loss.weight(s)) <= 1)


def test_loss_as_a_prefix_of_the_residual():
    """`(Tukey, None)`: the data is robustified, a stiff prior that disagrees with it is not (a
    Tukey loss on the prior would reject it)."""
    data = outlier_data()

    def residual(x, data):
        return similarity_residual(x, data), 100.0 * (x["log_scale"] - jnp.log(1.25))

    start = robust_fit(data, LOSSES["Huber"], similarity_start()).value
    sol = ls.least_squares(residual, start, data, loss=(ls.Tukey(0.5), None))
    rotation, _, _ = umeyama(data[0][1::4], data[1][1::4])
    assert sol.status_name == "CONVERGED"
    np.testing.assert_allclose(sol.value["rotation"].as_matrix(), rotation, atol=1e-8)
    np.testing.assert_allclose(jnp.exp(sol.value["log_scale"]), 1.25, atol=2e-3)
    with pytest.raises(ValueError, match="prefix"):
        ls.least_squares(residual, start, data, loss=(ls.Tukey(0.5),))


# ---- statuses and errors ------------------------------------------------------------------------


def test_status_nonfinite_residual():
    with pytest.raises(ls.SolveError, match="NaN or infinite"):
        ls.least_squares(log_residual, jnp.array([-1.0]), jnp.array([1.0]), solver=ls.GaussNewton())
    at_start = ls.least_squares(
        log_residual, jnp.array([-1.0]), jnp.array([1.0]), solver=ls.GaussNewton(), throw=False
    )
    assert at_start.status == ls.Status.NONFINITE and at_start.iterations == 0
    # Gauss-Newton steps into log(x < 0) and stops there; LM rejects the step and converges
    gauss_newton = ls.least_squares(
        log_residual, jnp.array([np.e**3]), jnp.array([1.0]), solver=ls.GaussNewton(), throw=False
    )
    assert gauss_newton.status_name == "NONFINITE"
    np.testing.assert_allclose(gauss_newton.value, [np.e**3])  # the last finite iterate
    lm = ls.least_squares(log_residual, jnp.array([np.e**3]), jnp.array([1.0]))
    assert lm.status_name == "CONVERGED"
    np.testing.assert_allclose(lm.value, [1.0], atol=1e-8)


def test_status_under_vmap_never_raises():
    solve = jax.vmap(
        lambda x0: ls.least_squares(log_residual, x0, jnp.array([1.0]), solver=ls.GaussNewton())
    )
    sol = solve(jnp.array([[np.e**3], [2.0], [-1.0]]))
    assert list(sol.status_name) == ["NONFINITE", "CONVERGED", "NONFINITE"]
    np.testing.assert_allclose(sol.value[1], [1.0], atol=1e-8)


def test_status_diverged():
    """Gauss-Newton on $r(x) = x^{1/3}$ doubles $|x|$ at every step (x <- -2x)."""
    cube_root = lambda x, _: jnp.cbrt(x)  # noqa: E731
    gauss_newton = ls.GaussNewton(divergence_factor=100.0)
    sol = ls.least_squares(cube_root, jnp.array([1.0]), None, solver=gauss_newton, throw=False)
    assert sol.status_name == "DIVERGED" and sol.cost > 100 * sol.cost_history[0]
    np.testing.assert_allclose(sol.value, (-2.0) ** int(sol.iterations), rtol=1e-9)
    with pytest.raises(ls.SolveError, match="diverged"):
        ls.least_squares(cube_root, jnp.array([1.0]), None, solver=gauss_newton)


def test_status_max_iterations_and_the_iteration_table(capsys):
    data = similarity_data(jax.random.PRNGKey(0))
    sol = ls.least_squares(
        similarity_residual,
        similarity_start(),
        data,
        termination=ls.Termination(max_iterations=2),
        verbose=True,
    )
    assert sol.status == ls.Status.MAX_ITERATIONS and sol.status_name == "MAX_ITERATIONS"
    assert sol.iterations == 2 and sol.cost_history.shape == (3,)
    assert not np.any(np.isnan(sol.cost_history))
    jax.effects_barrier()
    lines = capsys.readouterr().out.strip().splitlines()
    assert lines[0].split() == [
        "iter",
        "cost",
        "cost_change",
        "|gradient|",
        "|step|",
        "gain_ratio",
        "damping",
        "accepted",
    ]
    assert [int(line.split()[0]) for line in lines[1:4]] == [0, 1, 2]
    printed_costs = [float(line.split()[1]) for line in lines[1:4]]
    np.testing.assert_allclose(printed_costs, sol.cost_history, rtol=1e-6)
    assert lines[4].startswith("MAX_ITERATIONS: 2 iterations")


def test_bad_arguments():
    data = similarity_data(jax.random.PRNGKey(0))
    with pytest.raises(TypeError, match="residuals must be arrays"):
        ls.least_squares(lambda x, _: x, lieax.SO3.identity(), None)
    with pytest.raises(TypeError, match="loss must be"):
        ls.least_squares(similarity_residual, similarity_start(), data, loss="huber")
    with pytest.raises(TypeError, match="solver"):
        ls.least_squares(similarity_residual, similarity_start(), data, solver="lm")
    with pytest.raises(ValueError, match="scale must be positive"):
        ls.Huber(0.0)


# ---- vmap ---------------------------------------------------------------------------------------


def test_vmap_over_64_problems_equals_a_loop_and_compiles_once():
    traces = []

    def residual(x, data):
        traces.append(None)
        return similarity_residual(x, data)

    keys = jax.random.split(jax.random.PRNGKey(5), 64)
    batch = jax.vmap(lambda key: similarity_data(key, noise=0.05))(keys)
    solve = jax.jit(jax.vmap(lambda data: ls.least_squares(residual, similarity_start(), data)))
    batched = solve(batch)
    traced = len(traces)
    solve(jax.tree_util.tree_map(lambda a: a + 0.01, batch))
    assert len(traces) == traced and solve._cache_size() == 1

    for i in range(64):
        data = jax.tree_util.tree_map(lambda a, i=i: a[i], batch)
        single = ls.least_squares(similarity_residual, similarity_start(), data)
        assert int(batched.status[i]) == int(single.status) == ls.Status.CONVERGED
        # the same decisions, up to rounding at a tolerance's threshold
        assert abs(int(batched.iterations[i]) - int(single.iterations)) <= 1
        for key in ("rotation", "translation", "log_scale"):
            np.testing.assert_allclose(
                jax.tree_util.tree_leaves(batched.value[key])[0][i],
                jax.tree_util.tree_leaves(single.value[key])[0],
                atol=1e-10,
            )
        np.testing.assert_allclose(batched.cost[i], single.cost, rtol=1e-9)


# ---- derivatives of a solution ------------------------------------------------------------------


@functools.cache
def diff_data():
    """The derivative tests' data (shapes of the tests above)."""
    return similarity_data(jax.random.PRNGKey(6), noise=0.1)


def solve_parameters(target, differentiation="implicit", loss=None):
    """The solution's parameters as one vector, and its cost, as functions of the targets."""
    sol = ls.least_squares(
        similarity_residual,
        similarity_start(),
        (diff_data()[0], target),
        loss=loss,
        differentiation=differentiation,
        **TIGHT,
    )
    value = sol.value
    flat = jnp.concatenate(
        [value["rotation"].parameters(), value["translation"], value["log_scale"][None]]
    )
    return flat, sol.cost


def central_differences(f, x, h=1e-5):
    columns = []
    for i in range(x.size):
        e = jnp.zeros(x.size).at[i].set(h).reshape(x.shape)
        columns.append((f(x + e) - f(x - e)) / (2 * h))
    return jnp.stack(columns, axis=-1).reshape(*columns[0].shape, *x.shape)


@pytest.fixture(scope="module")
def implicit_jacobian():
    return jax.jacfwd(solve_parameters)(diff_data()[1])


def test_implicit_derivatives_equal_finite_differences(implicit_jacobian):
    jac_value, jac_cost = implicit_jacobian
    fd = central_differences(lambda t: jnp.append(*solve_parameters(t)), diff_data()[1])
    fd_value, fd_cost = fd[:-1], fd[-1]
    np.testing.assert_allclose(jac_value, fd_value, atol=1e-6)
    np.testing.assert_allclose(jac_cost, fd_cost, atol=1e-6)
    assert np.abs(jac_value).max() > 0.01  # not trivially zero


def test_implicit_grad_equals_jacfwd(implicit_jacobian):
    jac_value, jac_cost = implicit_jacobian
    weights = jnp.linspace(-1.0, 1.0, 8)
    scalar = lambda t: solve_parameters(t)[0] @ weights + solve_parameters(t)[1]  # noqa: E731
    np.testing.assert_allclose(
        jax.grad(scalar)(diff_data()[1]),
        jnp.tensordot(weights, jac_value, 1) + jac_cost,
        atol=1e-12,
    )


def test_unrolled_derivatives_equal_implicit_after_convergence(implicit_jacobian):
    """Reverse mode through the unrolled loop (`jacrev`) against the implicit `jacfwd`."""
    jac_value, _ = implicit_jacobian
    unrolled = jax.jacrev(lambda t: solve_parameters(t, "unrolled")[0])(diff_data()[1])
    np.testing.assert_allclose(unrolled, jac_value, atol=1e-6)


def test_implicit_derivatives_with_a_robust_loss():
    """The exact Hessian (robust second-order terms included) matches finite differences."""
    loss = ls.Cauchy(0.2)
    direction = jax.random.normal(jax.random.PRNGKey(7), diff_data()[1].shape)
    f = lambda t: solve_parameters(t, loss=loss)[0]  # noqa: E731
    _, jvp = jax.jvp(f, (diff_data()[1],), (direction,))
    h = 1e-5
    fd = (f(diff_data()[1] + h * direction) - f(diff_data()[1] - h * direction)) / (2 * h)
    np.testing.assert_allclose(jvp, fd, atol=1e-6)
