"""Solver fault tests of `lieax.lstsq.least_squares` and `lieax.factorgraph` (issue 17):
residuals scaled by constants from 1e-12 to 1e12 (same status and iterates), a start where the
gradient is tiny but not zero (a step must be tried), outliers, non-finite starts and data (the
start back unchanged with `NONFINITE` and a `NonFiniteStartError` naming the input), one bad
problem in a vmapped batch, loss scales that are not positive (concrete and traced) and NumPy
integers for iteration counts.

Residual functions are module-level, so each (problem, solver, dtype) compiles once; scales and
data are traced arguments.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

jax.config.update("jax_enable_x64", True)

import lieax  # noqa: E402
import lieax.lstsq as ls  # noqa: E402
from lieax.factorgraph import Factor, FactorGraph, Var  # noqa: E402

SOLVERS = {"LM": ls.LevenbergMarquardt(), "GN": ls.GaussNewton()}
DTYPES = {"f64": jnp.float64, "f32": jnp.float32}


# ---- problems: residuals times a traced constant `scale` -------------------------------------


def rosenbrock(x, data):
    (scale,) = data
    return scale * jnp.stack([10.0 * (x[1] - x[0] ** 2), 1.0 - x[0]])


def exponential_fit(x, data):
    scale, t, y = data
    return scale * (x[0] * jnp.exp(-x[1] * t) - y)


def rotation_fit(rotation, data):
    scale, source, target = data
    return scale * jax.vmap(lambda p, q: rotation @ p - q)(source, target)


def _rotation_pair(n=12, noise=0.01, outliers=0, seed=0):
    rng = np.random.default_rng(seed)
    truth = lieax.SO3.exp(jnp.array([0.3, -0.2, 0.5]))
    source = rng.normal(size=(n, 3))
    target = np.asarray(truth @ jnp.asarray(source)) + noise * rng.normal(size=(n, 3))
    target[:outliers] += rng.normal(size=(outliers, 3)) * 5.0
    return truth, source, target


def _problem(name, dtype):
    """`(residual_fn, x0, data(scale))` in `dtype`."""
    if name == "rosenbrock":
        return rosenbrock, jnp.array([-1.2, 1.0], dtype), lambda s: (jnp.asarray(s, dtype),)
    if name == "exponential":
        t = np.linspace(0.0, 4.0, 20)
        y = 2.5 * np.exp(-1.3 * t) + 0.01 * np.sin(7.0 * t)  # a nonzero residual at the optimum
        data = (jnp.asarray(t, dtype), jnp.asarray(y, dtype))
        return (
            exponential_fit,
            jnp.array([1.0, 0.5], dtype),
            lambda s: (jnp.asarray(s, dtype), *data),
        )
    _, source, target = _rotation_pair()
    data = (jnp.asarray(source, dtype), jnp.asarray(target, dtype))
    x0 = lieax.SO3.exp(jnp.zeros(3, dtype))
    return rotation_fit, x0, lambda s: (jnp.asarray(s, dtype), *data)


def _array(value):
    return np.asarray(getattr(value, "_params", value))


# ---- scale invariance ------------------------------------------------------------------------


@pytest.mark.parametrize("solver", SOLVERS)
@pytest.mark.parametrize("dtype", DTYPES)
@pytest.mark.parametrize("name", ["rosenbrock", "exponential", "rotation"])
def test_residual_scale_changes_neither_status_nor_iterates(name, dtype, solver):
    residual_fn, x0, data = _problem(name, DTYPES[dtype])
    kwargs = dict(
        solver=SOLVERS[solver], termination=ls.Termination(max_iterations=200), throw=False
    )
    reference = ls.least_squares(residual_fn, x0, data(1.0), **kwargs)
    assert reference.status_name == "CONVERGED"
    # powers of two scale every quantity exactly: the same iterates, bit for bit
    for scale in (2.0**-30, 2.0**30):
        scaled = ls.least_squares(residual_fn, x0, data(scale), **kwargs)
        assert scaled.status_name == "CONVERGED"
        assert int(scaled.iterations) == int(reference.iterations)
        np.testing.assert_array_equal(_array(scaled.value), _array(reference.value))
    # any other constant from 1e-12 to 1e12: the same status and solution (up to rounding)
    rtol = 1e-9 if dtype == "f64" else 2e-4
    for scale in (1e-12, 1e-6, 1e6, 1e12):
        scaled = ls.least_squares(residual_fn, x0, data(scale), **kwargs)
        assert scaled.status_name == "CONVERGED", scale
        assert int(scaled.iterations) >= 1
        if dtype == "f64":
            assert abs(int(scaled.iterations) - int(reference.iterations)) <= 1
        np.testing.assert_allclose(
            _array(scaled.value), _array(reference.value), rtol=rtol, atol=rtol
        )


def tiny_gradient(x, target):
    """A large constant residual next to a small one that depends on `x`: the cosine between
    the residual and the Jacobian's columns at x = 0 is ~3e-11, below the gradient tolerance,
    but the optimum is at `target`."""
    return jnp.concatenate([jnp.array([1e6], x.dtype), 1e-5 * (x - target)])


@pytest.mark.parametrize("solver", SOLVERS)
def test_a_start_that_is_not_stationary_tries_a_step(solver):
    target = jnp.array([3.0, -1.0])
    solution = ls.least_squares(tiny_gradient, jnp.zeros(2), target, solver=SOLVERS[solver])
    assert int(solution.iterations) >= 1
    np.testing.assert_allclose(solution.value, target, rtol=1e-3)


def offset(x, target):
    return x - target


@pytest.mark.parametrize("solver", SOLVERS)
def test_an_exactly_stationary_start_converges_at_iteration_zero(solver):
    target = jnp.array([3.0, -1.0])
    solution = ls.least_squares(offset, target, target, solver=SOLVERS[solver])
    assert solution.status_name == "CONVERGED"
    assert int(solution.iterations) == 0
    np.testing.assert_array_equal(solution.value, target)


# ---- outliers --------------------------------------------------------------------------------


def test_outliers_with_a_robust_loss_and_a_scaled_residual():
    truth, source, target = _rotation_pair(n=40, outliers=8, seed=3)
    data = (jnp.asarray(1.0), jnp.asarray(source), jnp.asarray(target))
    x0 = lieax.SO3.identity()
    plain = ls.least_squares(rotation_fit, x0, data)
    robust = ls.least_squares(rotation_fit, x0, data, loss=ls.Cauchy(0.05))

    def error(solution):
        return float(jnp.linalg.norm((truth.inverse() @ solution.value).log()))

    assert robust.status_name == "CONVERGED"
    assert error(robust) < 5e-3 < error(plain)
    # the residual and the loss's scale scaled together: the same solve
    scaled = ls.least_squares(
        rotation_fit, x0, (jnp.asarray(1e6), *data[1:]), loss=ls.Cauchy(0.05e6)
    )
    assert scaled.status_name == "CONVERGED"
    assert int(scaled.iterations) == int(robust.iterations)
    np.testing.assert_allclose(_array(scaled.value), _array(robust.value), atol=1e-10)


# ---- non-finite starts -----------------------------------------------------------------------


@pytest.mark.parametrize("solver", SOLVERS)
def test_a_nonfinite_start_comes_back_unchanged(solver):
    x0 = jnp.array([jnp.nan, 1.0])
    target = jnp.array([3.0, -1.0])
    solution = ls.least_squares(offset, x0, target, solver=SOLVERS[solver], throw=False)
    assert solution.status_name == "NONFINITE"
    assert int(solution.iterations) == 0
    np.testing.assert_array_equal(solution.value, x0)  # NaN where x0 has it
    with pytest.raises(ls.NonFiniteStartError, match=r"x0 has NaN or infinite entries \(1 of 2\)"):
        ls.least_squares(offset, x0, target, solver=SOLVERS[solver])
    with pytest.raises(ValueError, match=r"args has NaN"):
        ls.least_squares(offset, target, jnp.array([3.0, jnp.inf]), solver=SOLVERS[solver])


def first_only(x, data):
    return x[0] - data


def test_a_nonfinite_start_the_residual_does_not_read():
    x0 = (jnp.array([0.0]), jnp.array([jnp.nan]))
    solution = ls.least_squares(first_only, x0, jnp.array([2.0]), throw=False)
    assert solution.status_name == "NONFINITE"
    assert int(solution.iterations) == 0
    with pytest.raises(ls.NonFiniteStartError, match=r"x0\[1\]"):
        ls.least_squares(first_only, x0, jnp.array([2.0]))


def test_a_nonfinite_group_start_is_named():
    x0 = lieax.SO3(jnp.array([jnp.nan, 0.0, 0.0, 1.0]))
    _, source, target = _rotation_pair()
    with pytest.raises(ls.NonFiniteStartError, match=r"x0 \(SO3\)"):
        ls.least_squares(rotation_fit, x0, (jnp.asarray(1.0), source, target))


def log_ratio(x, target):
    return jnp.log(x) - jnp.log(target)


def test_a_nonfinite_residual_met_later_keeps_the_last_finite_iterate():
    # Gauss-Newton's first step from 10 lands at x < 0, where log is NaN
    x0, target = jnp.array([10.0]), jnp.array([1e-3])
    solution = ls.least_squares(log_ratio, x0, target, solver=ls.GaussNewton(), throw=False)
    assert solution.status_name == "NONFINITE"
    assert int(solution.iterations) >= 1
    assert np.all(np.isfinite(solution.value))
    with pytest.raises(ls.SolveError, match="after") as error:
        ls.least_squares(log_ratio, x0, target, solver=ls.GaussNewton())
    assert not isinstance(error.value, ls.NonFiniteStartError)
    # Levenberg-Marquardt rejects the step and gets there
    solution = ls.least_squares(log_ratio, x0, target)
    assert solution.status_name == "CONVERGED"
    np.testing.assert_allclose(solution.value, target, rtol=1e-8)


@pytest.mark.parametrize("solver", SOLVERS)
def test_one_bad_problem_does_not_disturb_a_vmapped_batch(solver):
    starts = jnp.array([[0.0, 0.0], [jnp.nan, 0.0], [1.0, 1.0], [0.5, -2.0]])
    targets = jnp.array([[3.0, -1.0], [3.0, -1.0], [2.0, 5.0], [jnp.inf, 1.0]])

    def solve(x0, target):
        return ls.least_squares(tiny_gradient, x0, target, solver=SOLVERS[solver], throw=False)

    batched = jax.vmap(solve)(starts, targets)
    np.testing.assert_array_equal(np.asarray(batched.status)[[1, 3]], ls.Status.NONFINITE)
    np.testing.assert_array_equal(np.asarray(batched.iterations)[[1, 3]], 0)
    np.testing.assert_array_equal(np.asarray(batched.value)[[1, 3]], np.asarray(starts)[[1, 3]])
    for b in (0, 2):
        single = solve(starts[b], targets[b])
        assert int(batched.status[b]) == int(single.status) == ls.Status.CONVERGED
        assert int(batched.iterations[b]) == int(single.iterations)
        np.testing.assert_allclose(batched.value[b], single.value, rtol=1e-12)


# ---- loss scales -----------------------------------------------------------------------------


@pytest.mark.parametrize("loss", [ls.Huber, ls.Cauchy, ls.Tukey, ls.GemanMcClure])
def test_concrete_loss_scales_are_checked(loss):
    for scale in (jnp.array(-1.0), np.float32(0.0), jnp.inf, float("nan"), -2):
        with pytest.raises(ValueError, match=f"{loss.__name__} scale must be positive"):
            loss(scale)
    with pytest.raises(TypeError, match="real number"):
        loss("1.0")
    assert float(loss(np.float64(0.5)).scale) == 0.5


def test_a_traced_loss_scale_that_is_not_positive_gives_nonfinite():
    target = jnp.array([3.0, -1.0])

    def solve(scale):
        return ls.least_squares(offset, jnp.zeros(2), target, loss=ls.Huber(scale), throw=False)

    batched = jax.vmap(solve)(jnp.array([1.0, -1.0, 0.0, 0.5]))
    assert list(batched.status_name) == ["CONVERGED", "NONFINITE", "NONFINITE", "CONVERGED"]
    np.testing.assert_array_equal(batched.iterations[1:3], 0)
    np.testing.assert_allclose(np.asarray(batched.value)[[0, 3]], [target, target], rtol=1e-8)
    # a loss rebuilt by a tree map (as transformations do) is unchecked; a solve names it
    negative = jax.tree_util.tree_map(lambda c: -c, ls.Huber(1.0))
    with pytest.raises(ls.NonFiniteStartError, match="Huber has scale -1.0"):
        ls.least_squares(offset, jnp.zeros(2), target, loss=negative)


def test_derivatives_with_respect_to_a_loss_scale_still_work():
    _, source, target = _rotation_pair(n=20, outliers=4, seed=1)

    def cost(scale):
        data = (jnp.asarray(1.0), jnp.asarray(source), jnp.asarray(target))
        return ls.least_squares(
            rotation_fit, lieax.SO3.identity(), data, loss=ls.Cauchy(scale)
        ).cost

    step = 1e-6
    numeric = (cost(0.5 + step) - cost(0.5 - step)) / (2 * step)
    np.testing.assert_allclose(jax.grad(cost)(0.5), numeric, rtol=1e-5)


# ---- iteration counts ------------------------------------------------------------------------


def test_numpy_integers_are_iteration_counts():
    target = jnp.array([3.0, -1.0])
    x0 = jnp.zeros(2)
    for count in (np.int64(30), np.int32(30), np.uint8(30)):
        solution = ls.least_squares(
            tiny_gradient, x0, target, termination=ls.Termination(max_iterations=count)
        )
        assert solution.cost_history.shape == (31,)
    for bad in (3.0, -1, np.float64(2.0), "3"):
        with pytest.raises(ValueError, match="max_iterations must be a non-negative int"):
            ls.Termination(max_iterations=bad)


# ---- factor graphs ---------------------------------------------------------------------------


def fg_offset(x, target):
    return x - target


def fg_rosenbrock(x, scale):
    return scale[0] * jnp.stack([10.0 * (x[1] - x[0] ** 2), 1.0 - x[0]])


def _fg_offset_graph():
    x = Var(jnp.zeros((2, 2)), name="x")
    targets = jnp.array([[3.0, -1.0], [0.5, 2.0]])
    factor = Factor(fg_offset, (x[np.arange(2)],), targets, name="offset")
    return FactorGraph([factor], check_gauge=False), targets


@pytest.fixture(scope="module")
def offset_graph():
    return _fg_offset_graph()


@pytest.mark.parametrize("algorithm", [ls.LevenbergMarquardt.gtsam(), ls.GaussNewton()])
def test_factor_graph_stationary_start_converges_at_iteration_zero(offset_graph, algorithm):
    graph, targets = offset_graph
    result = graph.solve(values=(targets,), solver=algorithm)
    assert int(result.status) == ls.Status.CONVERGED  # Levenberg-Marquardt said DIVERGED
    assert int(result.iterations) == 0
    np.testing.assert_array_equal(result.values[0], targets)
    result = graph.solve(solver=algorithm)  # from zeros: a step is tried
    assert int(result.status) == ls.Status.CONVERGED
    assert int(result.iterations) >= 1
    np.testing.assert_allclose(result.values[0], targets, atol=1e-6)


def test_factor_graph_nonfinite_start(offset_graph):
    graph, targets = offset_graph
    start = jnp.array([[jnp.nan, 0.0], [0.0, 0.0]])
    result = graph.solve(values=(start,), throw=False)
    assert int(result.status) == ls.Status.NONFINITE
    assert int(result.iterations) == 0
    np.testing.assert_array_equal(result.values[0], start)
    with pytest.raises(ls.NonFiniteStartError, match=r"values\['x'\] has NaN"):
        graph.solve(values=(start,))
    bad_data = [(targets.at[1, 0].set(jnp.inf), None, None)]
    with pytest.raises(ValueError, match="data of factor 'offset' has NaN"):
        graph.solve(data=bad_data)
    # one bad problem in a vmapped batch of starts (an array Var under vmap)
    starts = jnp.stack([jnp.zeros((2, 2)), start, jnp.ones((2, 2))])
    batched = jax.vmap(lambda x: graph.solve(values=(x,), throw=False))(starts)
    np.testing.assert_array_equal(batched.status, [0, ls.Status.NONFINITE, 0])
    np.testing.assert_array_equal(batched.values[0][1], start)
    single = graph.solve(values=(starts[2],))
    np.testing.assert_allclose(batched.values[0][2], single.values[0], rtol=1e-12)
    assert int(batched.iterations[2]) == int(single.iterations)


def test_factor_graph_relative_tests_are_scale_invariant():
    """With `absolute_function_tolerance=0` (GTSAM's absolute test off) and Marquardt damping, scaling the
    residual by a power of two changes nothing; `max_iterations` takes NumPy integers."""
    x = Var(jnp.array([[-1.2, 1.0]]), name="x")
    factor = Factor(fg_rosenbrock, (x[np.array([0])],), jnp.ones((1, 1)), name="rosenbrock")
    graph = FactorGraph([factor], check_gauge=False)
    options = dict(
        solver=ls.LevenbergMarquardt.gtsam(scaling="clipped", damping_update="nielsen",
                                           min_diagonal=1e-30),
        termination=ls.Termination.gtsam(absolute_function_tolerance=0.0,
                                         function_tolerance=1e-10, max_iterations=np.int64(200)),
    )  # fmt: skip
    reference = graph.solve(**options)
    assert int(reference.status) == ls.Status.CONVERGED
    np.testing.assert_allclose(reference.values[0], [[1.0, 1.0]], atol=1e-6)
    for scale in (2.0**-20, 2.0**20):
        scaled = graph.solve(data=[(jnp.full((1, 1), scale), None, None)], **options)
        assert int(scaled.status) == ls.Status.CONVERGED
        assert int(scaled.iterations) == int(reference.iterations)
        np.testing.assert_array_equal(scaled.values[0], reference.values[0])
    with pytest.raises(ValueError, match="max_iterations must be a non-negative int"):
        graph.solve(termination=ls.Termination.gtsam(max_iterations=2.5))
