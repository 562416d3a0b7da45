r"""Badly scaled nonlinear regression: problems of the NIST StRD nonlinear regression set, as
published and rescaled so that one problem's parameters span twelve orders of magnitude, solved
by `lieax.lstsq.least_squares` (Levenberg-Marquardt) and by MINPACK's `lmder` (through
`scipy.optimize.least_squares(method="lm")`). Every problem MINPACK solves to four significant
digits of NIST's certified values, lieax must solve too: with its default solver, or, where
Nielsen's damping rule does not (`MINPACK_RULE`), with MINPACK's trust region
(`LevenbergMarquardt(damping_update="minpack")`), which takes MINPACK's own steps.

Models, data, starting points and certified values are NIST's
(https://www.itl.nist.gov/div898/strd/nls/nls_main.shtml). In a rescaled variant the unknowns are
$p = s \odot b$, with factors $s$ that put $p$ at magnitudes from $10^{-9}$ to $10^3$
(`RESCALED_MAGNITUDES`), and the model is evaluated at $b = p / s$: the data, the optimum and
every iterate of a scale-invariant method are those of the published problem.

The problem definitions are shared with `benchmarks/regression.py`.
"""

import dataclasses
import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest

jax.config.update("jax_enable_x64", True)

import lieax.lstsq as ls  # noqa: E402

RESCALED_MAGNITUDES = (1e-9, 1e3)  # the smallest and largest |p_j| of a rescaled problem
MAX_ITERATIONS = 1000
LEVENBERG_MARQUARDT = ls.LevenbergMarquardt()  # the default solver
MINPACK_DAMPING = ls.LevenbergMarquardt(damping_update="minpack")
SIGNIFICANT = 1e-4  # four significant digits: |b - b_certified| <= 1e-4 |b_certified|


@dataclasses.dataclass(frozen=True)
class Problem:
    """A NIST StRD problem: `model(b, x, xp)` with `xp` NumPy or `jax.numpy`, its data, NIST's
    two starting points and the certified parameters."""

    name: str
    model: object
    x: tuple
    y: tuple
    starts: tuple
    certified: tuple


def _misra1a(b, x, xp):
    return b[0] * (1 - xp.exp(-b[1] * x))


def _chwirut(b, x, xp):
    return xp.exp(-b[0] * x) / (b[1] + b[2] * x)


def _misra1d(b, x, xp):
    return b[0] * b[1] * x / (1 + b[1] * x)


def _lanczos(b, x, xp):
    return b[0] * xp.exp(-b[1] * x) + b[2] * xp.exp(-b[3] * x) + b[4] * xp.exp(-b[5] * x)


def _rat42(b, x, xp):
    return b[0] / (1 + xp.exp(b[1] - b[2] * x))


def _mgh10(b, x, xp):
    return b[0] * xp.exp(b[1] / (x + b[2]))


def _mgh17(b, x, xp):
    return b[0] + b[1] * xp.exp(-x * b[3]) + b[2] * xp.exp(-x * b[4])


def _mgh09(b, x, xp):
    return b[0] * (x**2 + x * b[1]) / (x**2 + x * b[2] + b[3])


def _thurber(b, x, xp):
    numerator = b[0] + b[1] * x + b[2] * x**2 + b[3] * x**3
    return numerator / (1 + b[4] * x + b[5] * x**2 + b[6] * x**3)


def _rat43(b, x, xp):
    return b[0] / (1 + xp.exp(b[1] - b[2] * x)) ** (1 / b[3])


def _eckerle4(b, x, xp):
    return b[0] / b[1] * xp.exp(-0.5 * ((x - b[2]) / b[1]) ** 2)


# fmt: off
_MISRA_X = (77.6, 114.9, 141.1, 190.8, 239.9, 289.0, 332.8, 378.4, 434.8, 477.3, 536.8, 593.1,
            689.1, 760.0)
_MISRA_Y = (10.07, 14.73, 17.94, 23.93, 29.61, 35.18, 40.02, 44.82, 50.76, 55.05, 61.01, 66.40,
            75.47, 81.78)

PROBLEMS = (
    Problem(
        "Misra1a", _misra1a, _MISRA_X, _MISRA_Y,
        ((500.0, 1e-4), (250.0, 5e-4)),
        (2.3894212918e02, 5.5015643181e-04),
    ),
    Problem(
        "Chwirut2", _chwirut,
        (0.5, 1.0, 1.75, 3.75, 5.75, 0.875, 2.25, 3.25, 5.25, 0.75, 1.75, 2.75, 4.75, 0.625,
         1.25, 2.25, 4.25, 0.5, 3.0, 0.75, 3.0, 1.5, 6.0, 3.0, 6.0, 1.5, 3.0, 0.5, 2.0, 4.0,
         0.75, 2.0, 5.0, 0.75, 2.25, 3.75, 5.75, 3.0, 0.75, 2.5, 4.0, 0.75, 2.5, 4.0, 0.75, 2.5,
         4.0, 0.5, 6.0, 3.0, 0.5, 2.75, 0.5, 1.75),
        (92.9, 57.1, 31.05, 11.5875, 8.025, 63.6, 21.4, 14.25, 8.475, 63.8, 26.8, 16.4625,
         7.125, 67.3, 41.0, 21.15, 8.175, 81.5, 13.12, 59.9, 14.62, 32.9, 5.44, 12.56, 5.44,
         32.0, 13.95, 75.8, 20.0, 10.42, 59.5, 21.67, 8.55, 62.0, 20.2, 7.76, 3.75, 11.81, 54.7,
         23.7, 11.55, 61.3, 17.7, 8.74, 59.2, 16.3, 8.62, 81.0, 4.87, 14.62, 81.7, 17.17, 81.3,
         28.9),
        ((0.1, 0.01, 0.02), (0.15, 0.008, 0.010)),
        (1.6657666537e-01, 5.1653291286e-03, 1.2150007096e-02),
    ),
    Problem(
        "Misra1d", _misra1d, _MISRA_X, _MISRA_Y,
        ((500.0, 1e-4), (450.0, 3e-4)),
        (4.3736970754e02, 3.0227324449e-04),
    ),
    Problem(
        "Lanczos1", _lanczos,
        tuple(0.05 * i for i in range(24)),
        (2.513400000000e00, 2.044333373291e00, 1.668404436564e00, 1.366418021208e00,
         1.123232487372e00, 9.268897180037e-01, 7.679338563728e-01, 6.388775523106e-01,
         5.337835317402e-01, 4.479363617347e-01, 3.775847884350e-01, 3.197393199326e-01,
         2.720130773746e-01, 2.324965529032e-01, 1.996589546065e-01, 1.722704126914e-01,
         1.493405660168e-01, 1.300700206922e-01, 1.138119324644e-01, 1.000415587559e-01,
         8.833209084540e-02, 7.833544019350e-02, 6.976693743449e-02, 6.239312536719e-02),
        ((1.2, 0.3, 5.6, 5.5, 6.5, 7.6), (0.5, 0.7, 3.6, 4.2, 4.0, 6.3)),
        (9.5100000027e-02, 1.0000000001e00, 8.6070000013e-01, 3.0000000002e00,
         1.5575999998e00, 5.0000000001e00),
    ),
    Problem(
        "Rat42", _rat42,
        (9.0, 14.0, 21.0, 28.0, 42.0, 57.0, 63.0, 70.0, 79.0),
        (8.93, 10.8, 18.59, 22.33, 39.35, 56.11, 61.73, 64.62, 67.08),
        ((100.0, 1.0, 0.1), (75.0, 2.5, 0.07)),
        (7.2462237576e01, 2.6180768402e00, 6.7359200066e-02),
    ),
    Problem(
        "MGH10", _mgh10,
        tuple(50.0 + 5.0 * i for i in range(16)),
        (3.478e04, 2.861e04, 2.365e04, 1.963e04, 1.637e04, 1.372e04, 1.154e04, 9.744e03,
         8.261e03, 7.030e03, 6.005e03, 5.147e03, 4.427e03, 3.820e03, 3.307e03, 2.872e03),
        ((2.0, 4e5, 2.5e4), (0.02, 4000.0, 250.0)),
        (5.6096364710e-03, 6.1813463463e03, 3.4522363462e02),
    ),
    Problem(
        "BoxBOD", _misra1a,
        (1.0, 2.0, 3.0, 5.0, 7.0, 10.0),
        (109.0, 149.0, 149.0, 191.0, 213.0, 224.0),
        ((1.0, 1.0), (100.0, 0.75)),
        (2.1380940889e02, 5.4723748542e-01),
    ),
    Problem(
        "MGH17", _mgh17,
        tuple(10.0 * i for i in range(33)),
        (0.844, 0.908, 0.932, 0.936, 0.925, 0.908, 0.881, 0.850, 0.818, 0.784, 0.751, 0.718,
         0.685, 0.658, 0.628, 0.603, 0.580, 0.558, 0.538, 0.522, 0.506, 0.490, 0.478, 0.467,
         0.457, 0.448, 0.438, 0.431, 0.424, 0.420, 0.414, 0.411, 0.406),
        ((50.0, 150.0, -100.0, 1.0, 2.0), (0.5, 1.5, -1.0, 0.01, 0.02)),
        (3.7541005211e-01, 1.9358469127e00, -1.4646871366e00, 1.2867534640e-02,
         2.2122699662e-02),
    ),
    Problem(
        "MGH09", _mgh09,
        (4.0, 2.0, 1.0, 0.5, 0.25, 0.167, 0.125, 0.1, 0.0833, 0.0714, 0.0625),
        (0.1957, 0.1947, 0.1735, 0.1600, 0.0844, 0.0627, 0.0456, 0.0342, 0.0323, 0.0235,
         0.0246),
        ((25.0, 39.0, 41.5, 39.0), (0.25, 0.39, 0.415, 0.39)),
        (1.9280693458e-01, 1.9128232873e-01, 1.2305650693e-01, 1.3606233068e-01),
    ),
    Problem(
        "Thurber", _thurber,
        (-3.067, -2.981, -2.921, -2.912, -2.840, -2.797, -2.702, -2.699, -2.633, -2.481, -2.363,
         -2.322, -1.501, -1.460, -1.274, -1.212, -1.100, -1.046, -0.915, -0.714, -0.566, -0.545,
         -0.400, -0.309, -0.109, -0.103, 0.010, 0.119, 0.377, 0.790, 0.963, 1.006, 1.115, 1.572,
         1.841, 2.047, 2.200),
        (80.574, 84.248, 87.264, 87.195, 89.076, 89.608, 89.868, 90.101, 92.405, 95.854,
         100.696, 101.060, 401.672, 390.724, 567.534, 635.316, 733.054, 759.087, 894.206,
         990.785, 1090.109, 1080.914, 1122.643, 1178.351, 1260.531, 1273.514, 1288.339,
         1327.543, 1353.863, 1414.509, 1425.208, 1421.384, 1442.962, 1464.350, 1468.705,
         1447.894, 1457.628),
        ((1000.0, 1000.0, 400.0, 40.0, 0.7, 0.3, 0.0),
         (1300.0, 1500.0, 500.0, 75.0, 1.0, 0.4, 0.05)),
        (1.2881396800e03, 1.4910792535e03, 5.8323836877e02, 7.5416644291e01, 9.6629502864e-01,
         3.9797285797e-01, 4.9727297349e-02),
    ),
    Problem(
        "Rat43", _rat43,
        tuple(float(i) for i in range(1, 16)),
        (16.08, 33.83, 65.80, 97.20, 191.55, 326.20, 386.87, 520.53, 590.03, 651.92, 724.93,
         699.56, 689.96, 637.56, 717.41),
        ((100.0, 10.0, 1.0, 1.0), (700.0, 5.0, 0.75, 1.3)),
        (6.9964151270e02, 5.2771253025e00, 7.5962938329e-01, 1.2792483859e00),
    ),
    Problem(
        "Eckerle4", _eckerle4,
        (400.0, 405.0, 410.0, 415.0, 420.0, 425.0, 430.0, 435.0, 436.5, 438.0, 439.5, 441.0,
         442.5, 444.0, 445.5, 447.0, 448.5, 450.0, 451.5, 453.0, 454.5, 456.0, 457.5, 459.0,
         460.5, 462.0, 463.5, 465.0, 470.0, 475.0, 480.0, 485.0, 490.0, 495.0, 500.0),
        (0.0001575, 0.0001699, 0.0002350, 0.0003102, 0.0004917, 0.0008710, 0.0017418, 0.0046400,
         0.0065895, 0.0097302, 0.0149002, 0.0237310, 0.0401683, 0.0712559, 0.1264458, 0.2073413,
         0.2902366, 0.3445623, 0.3698049, 0.3668534, 0.3106727, 0.2078154, 0.1164354, 0.0616764,
         0.0337200, 0.0194023, 0.0117831, 0.0074357, 0.0022732, 0.0008800, 0.0004579, 0.0002345,
         0.0001586, 0.0001143, 0.0000710),
        ((1.0, 10.0, 500.0), (1.5, 5.0, 450.0)),
        (1.5543827178e00, 4.0888321754e00, 4.5154121844e02),
    ),
)
# fmt: on


def rescaling(problem) -> np.ndarray:
    """Powers of ten $s$ that put $|s_j b_j|$ (certified $b$) near magnitudes spread
    geometrically over `RESCALED_MAGNITUDES`, the first parameter the smallest."""
    magnitudes = np.geomspace(*RESCALED_MAGNITUDES, len(problem.certified))
    return 10.0 ** np.round(np.log10(magnitudes / np.abs(problem.certified)))


def cases(problem):
    """`(variant, start, scale)` for both NIST starts, published (`s = 1`) and rescaled."""
    ones = np.ones(len(problem.certified))
    return [
        (variant, start, scale)
        for variant, scale in (("published", ones), ("rescaled", rescaling(problem)))
        for start in (1, 2)
    ]


def solved(problem, b) -> bool:
    """Whether `b` matches the certified parameters to four significant digits."""
    certified = np.asarray(problem.certified)
    return bool(np.all(np.abs(np.asarray(b) - certified) <= SIGNIFICANT * np.abs(certified)))


# ---- the two solvers -------------------------------------------------------------------------


@functools.cache
def residual_fn(problem):
    r"""The residual $f(p / s, x) - y$ of `problem` in the unknowns $p = s \odot b$, one
    function object per problem (so that every solve of it shares one compilation)."""

    def residual(p, data):
        x, y, scale = data
        return problem.model(p / scale, x, jnp) - y

    return residual


@functools.partial(jax.jit, static_argnums=0)
def solve_lieax(residual, solver, starts, scales, x, y):
    """`lieax.lstsq.least_squares` from every row of `starts` (unknowns $p$) with the matching
    row of `scales`, under `vmap`."""

    def solve(start, scale):
        return ls.least_squares(
            residual,
            start,
            (x, y, scale),
            solver=solver,
            termination=ls.Termination(max_iterations=MAX_ITERATIONS),
            throw=False,
        )

    return jax.vmap(solve)(starts, scales)


def lieax_results(problem, solver=LEVENBERG_MARQUARDT):
    """`[(b, iterations, status name)]` in the order of `cases(problem)`."""
    rows = cases(problem)
    scales = np.stack([scale for _, _, scale in rows])
    starts = np.stack([problem.starts[start - 1] for _, start, _ in rows]) * scales
    solution = solve_lieax(
        residual_fn(problem), solver, starts, scales, np.asarray(problem.x), np.asarray(problem.y)
    )
    values = np.asarray(solution.value) / scales
    return list(zip(values, np.asarray(solution.iterations), solution.status_name))


@functools.cache
def model_jacobian(problem):
    """The jitted Jacobian `(p, s) ↦ ∂/∂p model(p / s)` (one program for the problem's four
    cases)."""
    x = np.asarray(problem.x)
    return jax.jit(jax.jacfwd(lambda p, scale: problem.model(p / scale, x, jnp)))


def minpack_result(problem, start, scale):
    """`(b, function evaluations, success)` of MINPACK's `lmder` (SciPy's `method="lm"` with
    `x_scale="jac"`, its mode 1) on the problem in the unknowns $p$."""
    from scipy.optimize import least_squares

    x, y = np.asarray(problem.x), np.asarray(problem.y)
    jac = model_jacobian(problem)

    def fun(p):
        with np.errstate(over="ignore", invalid="ignore"):  # MINPACK's trial points may overflow
            return problem.model(p / scale, x, np) - y

    result = least_squares(
        fun,
        np.asarray(problem.starts[start - 1]) * scale,
        jac=lambda p: np.asarray(jac(p, scale)),
        method="lm",
        x_scale="jac",
        ftol=1e-10,
        xtol=1e-10,
        gtol=1e-10,
        max_nfev=10000,
    )
    return result.x / scale, result.nfev, result.success


def minpack_results(problem):
    """`minpack_result` in the order of `cases(problem)`."""
    return [minpack_result(problem, start, scale) for _, start, scale in cases(problem)]


# ---- the suite -------------------------------------------------------------------------------

# Nielsen's damping rule (the default) leads MGH10 from NIST's first start (b = (2, 4e5, 2.5e4),
# residuals of 1e7) into the valley b1 -> 0, where it stops (no scaling fixes this: all three were
# measured); MINPACK's trust region does not. These cases are solved with MINPACK_DAMPING, which
# is not the default: from MGH17's first start it needs more than MAX_ITERATIONS under `vmap`
# (`benchmarks/regression.py` has the whole suite with both rules).
MINPACK_RULE = {("MGH10", 1)}

CASES = [
    pytest.param(problem, index, id=f"{problem.name}-{variant}-start{start}")
    for problem in PROBLEMS
    for index, (variant, start, _) in enumerate(cases(problem))
]


@pytest.fixture(scope="module")
def lieax_solutions():
    """`lieax_results` of every problem, computed once: with the default solver, and with
    `MINPACK_DAMPING` for the starts of `MINPACK_RULE`."""
    solutions = {}
    for problem in PROBLEMS:
        results = lieax_results(problem)
        if any(name == problem.name for name, _ in MINPACK_RULE):
            minpack_rule = lieax_results(problem, MINPACK_DAMPING)
            results = [
                minpack_rule[index] if (problem.name, start) in MINPACK_RULE else result
                for index, ((_, start, _), result) in enumerate(zip(cases(problem), results))
            ]
        solutions[problem.name] = results
    return solutions


@pytest.fixture(scope="module")
def minpack_solutions():
    """`minpack_results` of every problem, computed once."""
    return {problem.name: minpack_results(problem) for problem in PROBLEMS}


@pytest.mark.parametrize("problem, index", CASES)
def test_lieax_solves_what_minpack_solves(problem, index, lieax_solutions, minpack_solutions):
    b_minpack, _, _ = minpack_solutions[problem.name][index]
    if not solved(problem, b_minpack):
        pytest.skip("MINPACK does not reach the certified values from here either")
    b, iterations, status = lieax_solutions[problem.name][index]
    assert status == "CONVERGED"
    assert iterations < MAX_ITERATIONS
    assert solved(problem, b), f"{b} != {problem.certified} after {iterations} iterations"


def test_minpack_solves_most_of_the_suite(minpack_solutions):
    """The reference itself: MINPACK solves all but BoxBOD's first start (published and
    rescaled alike), so the suite is not vacuous."""
    unsolved = {
        (problem.name, variant, start)
        for problem in PROBLEMS
        for (variant, start, _), (b, _, _) in zip(cases(problem), minpack_solutions[problem.name])
        if not solved(problem, b)
    }
    assert unsolved == {("BoxBOD", "published", 1), ("BoxBOD", "rescaled", 1)}


@pytest.mark.parametrize("problem", PROBLEMS, ids=lambda problem: problem.name)
def test_rescaling_changes_nothing(problem, lieax_solutions):
    r"""The default scaling is invariant under $b \to s \odot b$: published and rescaled variants
    reach the same point in about the same number of iterations."""
    results = lieax_solutions[problem.name]
    for start in (1, 2):
        b, iterations, _ = results[start - 1]
        b_rescaled, iterations_rescaled, _ = results[start + 1]
        np.testing.assert_allclose(b_rescaled, b, rtol=1e-6)
        assert abs(iterations_rescaled - iterations) <= max(2, iterations // 10)


@pytest.mark.parametrize("name", ["Misra1a", "Chwirut2", "Lanczos1", "Eckerle4"])
def test_minpack_damping_takes_minpacks_steps(name, minpack_solutions):
    r"""`LevenbergMarquardt(damping_update="minpack")` is MINPACK's `lmder`: on problems where
    rounding does not steer the path, it evaluates the residual as often as MINPACK does (an
    iteration of lieax is one evaluation; MINPACK also counts the one at the start)."""
    problem = next(problem for problem in PROBLEMS if problem.name == name)
    results = lieax_results(problem, MINPACK_DAMPING)
    for (b, iterations, status), (_, evaluations, _) in zip(results, minpack_solutions[name]):
        assert status == "CONVERGED"
        assert solved(problem, b)
        assert abs(int(iterations) + 1 - evaluations) <= 1


@pytest.mark.parametrize("scaling", ["clipped", "jacobi"])
@pytest.mark.parametrize("name", ["MGH09", "MGH17"])
def test_other_scalings_fail_a_rescaled_problem(name, scaling):
    """Marquardt's clipped diagonal (lieax's scaling before `scaling` existed) and Ceres' Jacobi
    scaling solve the published problem from both starts but not the rescaled one from NIST's
    first start, which the default solves (`test_lieax_solves_what_minpack_solves`): the reason
    for the default."""
    problem = next(problem for problem in PROBLEMS if problem.name == name)
    results = lieax_results(problem, ls.LevenbergMarquardt(scaling=scaling))
    for (variant, start, _), (b, _, _) in zip(cases(problem), results):
        if variant == "published":
            assert solved(problem, b)
        elif start == 1:
            assert not solved(problem, b)


def test_unknown_scaling_is_an_error():
    with pytest.raises(ValueError, match="scaling must be one of"):
        ls.LevenbergMarquardt(scaling="marquardt")
    with pytest.raises(ValueError, match="damping_update must be one of"):
        ls.LevenbergMarquardt(damping_update="ceres")


@pytest.mark.parametrize("differentiation", ["implicit", "unrolled"])
def test_derivative_of_a_rescaled_solve(differentiation):
    r"""$\partial b^\star / \partial y$ of rescaled Misra1a (unknowns $10^{-9}$ and $10^3$
    apart) through the scaled solver, against central finite differences of the solve."""
    problem = PROBLEMS[0]
    scale = rescaling(problem)
    start = np.asarray(problem.certified) * scale * 1.01
    x, y = np.asarray(problem.x), np.asarray(problem.y)

    def solve(y):
        solution = ls.least_squares(
            residual_fn(problem),
            start,
            (x, y, scale),
            termination=ls.Termination(
                max_iterations=200,
                function_tolerance=0.0,
                gradient_tolerance=0.0,
                parameter_tolerance=1e-14,
            ),
            differentiation=differentiation,
            throw=False,
        )
        return solution.value / scale

    direction = np.linspace(-1.0, 1.0, len(y))
    derivative = jax.jvp(solve, (y,), (direction,))[1]
    h = 1e-4
    finite_difference = (solve(y + h * direction) - solve(y - h * direction)) / (2 * h)
    assert np.all(np.isfinite(derivative))
    np.testing.assert_allclose(derivative, finite_difference, rtol=1e-5)


# ---- the factorization -----------------------------------------------------------------------


def test_spd_solve_is_invariant_under_diagonal_scaling():
    r"""$(D A D)^{-1} D b = D^{-1} A^{-1} b$ for $D$ spanning twelve orders of magnitude: the
    factorization's singularity test and fallback see the Jacobi-scaled matrix, so a well-posed
    badly scaled system is solved as the well-scaled one (the unscaled test would regularize it
    by $\sqrt{\varepsilon}\,10^6$ relative to its smallest diagonal entry)."""
    from lieax.lstsq._normal_equations import solve_spd

    rng = np.random.default_rng(0)
    jac = rng.normal(size=(20, 4))
    matrix, rhs = jac.T @ jac, jac.T @ rng.normal(size=20)
    scale = np.array([1e-9, 1e-5, 1e-1, 1e3])
    expected = np.linalg.solve(matrix, rhs)
    scaled = solve_spd(scale[:, None] * matrix * scale[None, :], scale * rhs)
    np.testing.assert_allclose(scale * np.asarray(scaled), expected, rtol=1e-9)


def test_spd_solve_still_regularizes_a_gauge():
    """A singular system (a variable no residual touches, a rank-deficient pair) falls back to
    the regularized solve: finite, zero on the untouched variable, and solving the system."""
    from lieax.lstsq._normal_equations import solve_spd

    jac = np.array([[1.0, 1.0, 0.0], [2.0, 2.0, 0.0], [1e3, 1e3, 0.0]])
    matrix, rhs = jac.T @ jac, jac.T @ np.array([1.0, -1.0, 2.0])
    solution = np.asarray(solve_spd(matrix, rhs))
    assert np.all(np.isfinite(solution))
    assert solution[2] == 0.0
    np.testing.assert_allclose(matrix @ solution, rhs, rtol=1e-6)
