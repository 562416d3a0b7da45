"""IMU preintegration and factors (`lieax.imu`): against GTSAM 4.3's
`PreintegratedImuMeasurements` (`TangentPreintegration`) and `ImuFactor` on random sample
streams; bias Jacobians and factor Jacobians against finite differences; the logarithmic-depth
variant against the sequential scan; batching and bad input."""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

import lieax.imu as imu
from lieax import SE3, SO3
from lieax import conventions as cv
from lieax.autodiff import rplus, tangent_dim, unflatten_tangents, value_and_jacobian

SAMPLES = 60
NOISE = dict(accel_noise_density=0.01, gyro_noise_density=1e-3, integration_sigma=1e-4)
PARAMS = imu.ImuParams.make_u(9.81, **NOISE)
ARM = SE3.from_rotation_and_translation(
    SO3.exp(jnp.array([0.1, 0.2, -0.3])), jnp.array([0.1, -0.05, 0.2])
)
PARAMS_ARM = PARAMS._replace(body_P_sensor=ARM)
BIAS = np.array([0.1, -0.2, 0.05, 0.01, -0.02, 0.03])

sequential = jax.jit(imu.preintegrate)
associative = jax.jit(imu.preintegrate_associative)
residual_and_jacobians = jax.jit(value_and_jacobian(imu.imu_residual, (0, 1, 2, 3, 4)))


def stream(seed, samples=SAMPLES, rate_scale=1.0):
    rng = np.random.default_rng(seed)
    gyro = rate_scale * rng.normal(size=(samples, 3))
    accel = rng.normal(size=(samples, 3)) + np.array([0.0, 0.0, 9.81])
    dt = 0.005 + 0.002 * rng.random(samples)
    return gyro, accel, dt


def vector(pim):
    return np.concatenate([pim.theta, pim.delta_p, pim.delta_v])


def relative(a, b):
    return np.max(np.abs(np.asarray(a) - b)) / np.max(np.abs(b))


# ---- GTSAM ----------------------------------------------------------------------------------------


def gtsam_params(gtsam, with_arm):
    params = gtsam.PreintegrationParams.MakeSharedU(9.81)
    params.setAccelerometerCovariance(NOISE["accel_noise_density"] ** 2 * np.eye(3))
    params.setGyroscopeCovariance(NOISE["gyro_noise_density"] ** 2 * np.eye(3))
    params.setIntegrationCovariance(NOISE["integration_sigma"] ** 2 * np.eye(3))
    params.setImuFactorErrorMode(gtsam.ImuFactorErrorMode.ComponentWise)
    if with_arm:
        rotation = gtsam.Rot3(np.asarray(ARM.rotation().as_matrix()))
        params.setBodyPSensor(gtsam.Pose3(rotation, np.asarray(ARM.translation())))
    return params


def gtsam_pim(gtsam, gyro, accel, dt, with_arm=False):
    bias = gtsam.imuBias.ConstantBias(BIAS[:3], BIAS[3:])
    pim = gtsam.PreintegratedImuMeasurements(gtsam_params(gtsam, with_arm), bias)
    for k in range(len(dt)):
        pim.integrateMeasurement(accel[k], gyro[k], dt[k])
    return pim


def gtsam_bias_jacobians(pim):
    """`[preintegrated_H_biasAcc, preintegrated_H_biasOmega]` (9×6), not wrapped in Python: read
    from the text serialization, where they are the two 9×3 matrices (column-major) in order."""
    tokens = pim.serialize().split()
    blocks = [
        np.array(tokens[k + 2 : k + 29], dtype=float).reshape(3, 9).T
        for k in range(len(tokens) - 1)
        if tokens[k] == "9" and tokens[k + 1] == "3"
    ]
    assert len(blocks) == 2
    return np.concatenate(blocks, axis=1)


def gtsam_pose(pose):
    return __import__("gtsam").Pose3(
        __import__("gtsam").Rot3(np.asarray(pose.rotation().as_matrix())),
        np.asarray(pose.translation()),
    )


@pytest.mark.parametrize("with_arm", [False, True])
def test_preintegration_matches_gtsam(with_arm):
    gtsam = pytest.importorskip("gtsam")
    gyro, accel, dt = stream(0)
    reference = gtsam_pim(gtsam, gyro, accel, dt, with_arm)
    ours = sequential(gyro, accel, dt, BIAS, PARAMS_ARM if with_arm else PARAMS)
    assert relative(vector(ours), reference.preintegrated()) < 1e-12
    assert relative(ours.delta_R.as_matrix(), reference.deltaRij().matrix()) < 1e-12
    assert relative(ours.delta_v, reference.deltaVij()) < 1e-12
    assert relative(ours.delta_p, reference.deltaPij()) < 1e-12
    assert float(ours.delta_t) == pytest.approx(reference.deltaTij(), rel=1e-14)
    assert relative(ours.covariance, reference.preintMeasCov()) < 1e-9
    assert relative(ours.jacobian_bias, gtsam_bias_jacobians(reference)) < 1e-9
    assert relative(ours.residual_covariance(), reference.residualCovariance()) < 1e-9


def test_predict_and_factor_match_gtsam():
    r"""`predict` as `PreintegrationBase::predict`; the residual and all five Jacobians, by
    autodiff and in closed form (`imu_jacobians`), as `ImuFactor.evaluateError` (ComponentWise),
    pose columns permuted to lieax's $(v, \omega)$."""
    gtsam = pytest.importorskip("gtsam")
    gyro, accel, dt = stream(1)
    reference = gtsam_pim(gtsam, gyro, accel, dt)
    pim = sequential(gyro, accel, dt, BIAS, PARAMS)
    rng = np.random.default_rng(2)
    poses = SE3.exp(jnp.asarray(rng.normal(size=(2, 6))))
    pose_i, pose_j = poses[0], poses[1]
    velocity_i, velocity_j = rng.normal(size=(2, 3))
    bias_i = BIAS + 0.01 * rng.normal(size=6)
    bias_g = gtsam.imuBias.ConstantBias(bias_i[:3], bias_i[3:])

    predicted = reference.predict(gtsam.NavState(gtsam_pose(pose_i), velocity_i), bias_g)
    pose_hat, velocity_hat = imu.predict(pim, pose_i, velocity_i, bias_i, PARAMS)
    assert relative(pose_hat.as_matrix(), predicted.pose().matrix()) < 1e-12
    assert relative(velocity_hat, predicted.velocity()) < 1e-12

    factor = gtsam.ImuFactor(1, 2, 3, 4, 5, reference)
    shapes = (6, 3, 6, 3, 6)
    h = [np.zeros((9, n), order="F") for n in shapes]
    error = factor.evaluateError(
        gtsam_pose(pose_i), velocity_i, gtsam_pose(pose_j), velocity_j, bias_g, *h
    )
    value, jacobians = residual_and_jacobians(
        pose_i, velocity_i, pose_j, velocity_j, bias_i, pim, PARAMS
    )
    closed_value, closed = imu.imu_jacobians(
        pose_i, velocity_i, pose_j, velocity_j, bias_i, pim, PARAMS
    )
    assert relative(value, error) < 1e-12
    assert relative(closed_value, error) < 1e-12
    for k, (ours, mine, theirs) in enumerate(zip(jacobians, closed, h)):
        if shapes[k] == 6 and k != 4:
            theirs = np.asarray(cv.se3_jacobian_from_gtsam(theirs, rows=False))
        assert relative(ours, theirs) < 1e-9, k
        assert relative(mine, theirs) < 1e-9, k


# ---- lieax only -----------------------------------------------------------------------------------


@pytest.mark.parametrize("variant", ["sequential", "associative"])
@pytest.mark.parametrize("rate_scale", [1.0, 0.0])
def test_bias_jacobians_by_finite_differences(variant, rate_scale):
    """`jacobian_bias` against central differences of re-integration with perturbed biases; at
    `rate_scale=0` the corrected rotation rate is exactly zero (gyro = gyro bias)."""
    integrate = {"sequential": sequential, "associative": associative}[variant]
    gyro, accel, dt = stream(3, rate_scale=rate_scale)
    gyro = gyro + BIAS[3:] * (rate_scale == 0.0)
    pim = integrate(gyro, accel, dt, BIAS, PARAMS_ARM)
    eps = 1e-6
    columns = [
        (vector(integrate(gyro, accel, dt, BIAS + eps * e, PARAMS_ARM))
         - vector(integrate(gyro, accel, dt, BIAS - eps * e, PARAMS_ARM))) / (2 * eps)
        for e in np.eye(6)
    ]  # fmt: skip
    np.testing.assert_allclose(pim.jacobian_bias, np.stack(columns, 1), atol=1e-8, rtol=1e-6)


def test_associative_agrees_to_first_order_in_dt():
    r"""The group product and GTSAM's tangent recursion are both consistent integrators of
    piecewise constant samples: they differ by $O(\delta t)$, halving when each sample is split
    in two (measured: 3e-6 relative for 60 samples at 5 ms and 1 rad/s)."""
    gyro, accel, dt = stream(4)
    differences = []
    for split in (1, 2):
        samples = (
            np.repeat(gyro, split, 0),
            np.repeat(accel, split, 0),
            np.repeat(dt / split, split),
        )
        a, b = sequential(*samples, BIAS, PARAMS), associative(*samples, BIAS, PARAMS)
        differences.append([
            relative(vector(b), vector(a)),
            relative(b.covariance, a.covariance),
            relative(b.jacobian_bias, a.jacobian_bias),
        ])  # fmt: skip
    differences = np.array(differences)
    assert np.all(differences[0] < 1e-3)
    np.testing.assert_allclose(differences[0] / differences[1], 2.0, rtol=0.05)


def test_associative_is_exact_for_constant_rotation_rate():
    r"""With a constant rate the product $\mathrm{Exp}(\omega\delta t)^N = \mathrm{Exp}(N\omega\delta t)$
    and the tangent recursion $\theta^+ = \theta + J_r^{-1}(\theta)\omega\delta t$ (which keeps
    $\theta \parallel \omega$) agree in $\theta$ exactly (13 samples: padded at two levels)."""
    for samples in (13,):
        gyro = np.tile([[0.3, -0.2, 0.5]], (samples, 1)) + BIAS[3:]
        accel = np.tile([[0.0, 0.0, 9.81]], (samples, 1))
        a = sequential(gyro, accel, 0.01, BIAS, PARAMS)
        b = associative(gyro, accel, 0.01, BIAS, PARAMS)
        np.testing.assert_allclose(b.theta, a.theta, atol=1e-14)
        np.testing.assert_allclose(b.theta, samples * 0.01 * np.array([0.3, -0.2, 0.5]), atol=1e-14)
        assert float(b.delta_t) == pytest.approx(0.01 * samples)


def test_vmap_over_intervals_equals_loop():
    streams = [stream(10 + k) for k in range(3)]
    gyro, accel, dt = (np.stack(x) for x in zip(*streams))
    batched = jax.jit(jax.vmap(imu.preintegrate, in_axes=(0, 0, 0, None, None)))(
        gyro, accel, dt, BIAS, PARAMS
    )
    for k, (g, a, d) in enumerate(streams):
        one = sequential(g, a, d, BIAS, PARAMS)
        for field in ("theta", "delta_p", "delta_v", "covariance", "jacobian_bias"):
            np.testing.assert_allclose(getattr(batched, field)[k], getattr(one, field), rtol=1e-12)


def test_bad_input():
    gyro, accel, dt = stream(5, samples=8)
    with pytest.raises(imu.ImuError, match="mismatched"):
        imu.preintegrate(gyro, accel[:-1], dt, BIAS, PARAMS)
    with pytest.raises(imu.ImuError, match=r"dt must be a scalar or have shape \(8,\)"):
        imu.preintegrate(gyro, accel, dt[:-1], BIAS, PARAMS)
    with pytest.raises(imu.ImuError, match=r"bias must be"):
        imu.preintegrate(gyro, accel, dt, BIAS[:3], PARAMS)
    with pytest.raises(imu.ImuError, match=r"\(samples, 3\)"):
        imu.preintegrate(gyro[:, :2], accel[:, :2], dt, BIAS, PARAMS)
    with pytest.raises(imu.ImuError, match=r"params.n_gravity must be \(3,\)"):
        imu.preintegrate(gyro, accel, dt, BIAS, PARAMS._replace(n_gravity=jnp.zeros(2)))
    bad_gyro = gyro.copy()
    bad_gyro[3, 1] = np.nan
    with pytest.raises(imu.ImuError, match="sample 3: non-finite"):
        imu.preintegrate(bad_gyro, accel, dt, BIAS, PARAMS)
    bad_dt = dt.copy()
    bad_dt[5] = 0.0
    with pytest.raises(imu.ImuError, match="sample 5: dt <= 0"):
        imu.preintegrate_associative(gyro, accel, bad_dt, BIAS, PARAMS)
    # Under vmap/jit: a status, and NaN rather than a number.
    batched = jax.jit(jax.vmap(imu.preintegrate, in_axes=(0, 0, 0, None, None)))(
        np.stack([gyro, bad_gyro, gyro]), np.stack([accel] * 3), np.stack([dt, dt, bad_dt]),
        BIAS, PARAMS,
    )  # fmt: skip
    np.testing.assert_array_equal(batched.valid, [True, False, False])
    assert np.all(np.isfinite(batched.covariance[0]))
    assert np.all(np.isnan(batched.theta[1:])) and np.all(np.isnan(batched.covariance[1:]))


# ---- factor Jacobians by finite differences ----------------------------------------------------

closed_form = jax.jit(imu.imu_jacobians)
# regime -> (gyro rate scale, rotation error r_θ imposed on pose_j, velocities, rotations of poses)
REGIMES = {
    "random": (1.0, None, "random", "random"),
    "zero_rate": (0.0, None, "random", "random"),
    "identity": (1.0, 0.0, "random", "random"),
    "near_identity_1e-9": (1.0, 1e-9, "random", "random"),
    "small_1e-4": (1.0, 1e-4, "random", "random"),
    "near_pi_1e-4": (1.0, np.pi - 1e-4, "random", "random"),
    "near_pi_1e-6": (1.0, np.pi - 1e-6, "random", "random"),
    "large_interval_rotation": (8.0, None, "random", "random"),
    "pure_translation": (0.0, None, "random", "identity"),
    "at_rest": (0.0, 0.0, "zero", "identity"),
}


def factor_state(regime, seed=6):
    r"""`(args, pim)` of one IMU factor in a regime: the interval's rate scale (0: the corrected
    rate is exactly zero), $\|r_\theta\|$ imposed through `pose_j`'s rotation (`None`: random),
    zero or random velocities, identity or random pose rotations. `at_rest`: a vehicle standing
    still, its prediction equal to `pose_j` (zero residual)."""
    rate_scale, angle, velocities, rotations = REGIMES[regime]
    rng = np.random.default_rng(seed)
    gyro, accel, dt = stream(7, rate_scale=rate_scale)
    gyro = gyro + BIAS[3:] * (rate_scale == 0.0)
    if regime == "at_rest":
        accel = np.tile(BIAS[:3] + [0.0, 0.0, 9.81], (SAMPLES, 1))
    pim = sequential(gyro, accel, dt, BIAS, PARAMS)
    bias_i = BIAS if regime == "at_rest" else BIAS + 0.01 * rng.normal(size=6)
    tangents = rng.normal(size=(2, 6))
    if rotations == "identity":
        tangents[:, 3:] = 0.0
    pose_i, pose_j = SE3.exp(jnp.asarray(tangents[0])), SE3.exp(jnp.asarray(tangents[1]))
    v_i, v_j = (np.zeros(3), np.zeros(3)) if velocities == "zero" else rng.normal(size=(2, 3))
    if regime == "at_rest":
        pose_j, v_j = imu.predict(pim, pose_i, v_i, bias_i, PARAMS)
    elif angle is not None:  # R_j = R_i R_c Exp(r_θ)^{-1}: the rotation error is r_θ
        axis = rng.normal(size=3)
        error = SO3.exp(jnp.asarray(angle * axis / np.linalg.norm(axis)))
        rotation_c = SO3.exp(pim.bias_corrected(bias_i)[:3])
        rotation_j = pose_i.rotation() @ rotation_c @ error.inverse()
        pose_j = SE3.from_rotation_and_translation(rotation_j, pose_j.translation())
    return (pose_i, v_i, pose_j, v_j, bias_i), pim


def numeric_jacobian(args, pim, eps):
    """Central differences of `imu_residual` in the right-local tangents of `args`, `(9, 24)`."""

    def f(delta):
        return imu.imu_residual(*rplus(args, unflatten_tangents(args, delta)), pim, PARAMS)

    steps = eps * np.eye(tangent_dim(args))
    differences = jax.jit(jax.vmap(f))(np.concatenate([steps, -steps]))
    return np.asarray((differences[: len(steps)] - differences[len(steps) :]).T / (2 * eps))


def stacked(blocks):
    return np.concatenate([np.asarray(b).reshape(9, -1) for b in blocks], 1)


@pytest.mark.parametrize("regime", list(REGIMES))
def test_factor_jacobians_by_finite_differences(regime):
    r"""The closed-form blocks (`imu_jacobians`) and the autodiff path (`value_and_jacobian` of
    `imu_residual`) against central differences (float64), and against each other; near $\pi$
    the step is below the distance to $\pi$ (where `Log` wraps)."""
    args, pim = factor_state(regime)
    value, blocks = closed_form(*args, pim, PARAMS)
    auto_value, auto_blocks = residual_and_jacobians(*args, pim, PARAMS)
    rotation_error = float(np.linalg.norm(value[:3]))
    angle = REGIMES[regime][1]
    if angle is not None:
        assert rotation_error == pytest.approx(angle, abs=1e-12)
    if regime == "at_rest":
        np.testing.assert_allclose(value, 0.0, atol=1e-12)
    eps = 1e-7 if regime.startswith("near_pi") else 1e-6
    numeric = numeric_jacobian(args, pim, eps)
    analytic = stacked(blocks)
    scale = max(1.0, np.max(np.abs(numeric)))
    np.testing.assert_allclose(analytic, numeric, atol=2e-7 * scale)
    np.testing.assert_allclose(value, auto_value, rtol=0, atol=1e-14)
    np.testing.assert_allclose(analytic, stacked(auto_blocks), rtol=0, atol=1e-12 * scale)


def test_factor_jacobians_batched_and_reverse():
    r"""`vmap(imu_jacobians)` over instances equals the unbatched blocks, and the rows of the
    pose_i block equal reverse-mode derivatives (`jax.vjp`) of the residual in local
    coordinates."""
    states = [factor_state(regime, seed=20 + k) for k, regime in enumerate(REGIMES)]
    args = jax.tree.map(lambda *x: jnp.stack(x), *[a for a, _ in states])
    pims = jax.tree.map(lambda *x: jnp.stack(x), *[p for _, p in states])
    values, blocks = jax.jit(jax.vmap(imu.imu_jacobians, in_axes=(0, 0, 0, 0, 0, 0, None)))(
        *args, pims, PARAMS
    )
    for k, (one_args, one_pim) in enumerate(states):
        value, one = closed_form(*one_args, one_pim, PARAMS)
        np.testing.assert_allclose(values[k], value, rtol=0, atol=1e-15)
        for b, b_one in zip(blocks, one):
            np.testing.assert_allclose(b[k], b_one, rtol=0, atol=1e-15)
    one_args, one_pim = states[0]

    def f(delta):
        return imu.imu_residual(
            *rplus(one_args, unflatten_tangents(one_args, delta)), one_pim, PARAMS
        )

    _, pullback = jax.vjp(f, jnp.zeros(tangent_dim(one_args)))
    rows = np.stack([pullback(e)[0] for e in jnp.eye(9)])
    _, one = closed_form(*one_args, one_pim, PARAMS)
    np.testing.assert_allclose(stacked(one), rows, rtol=0, atol=1e-12)
    rotating = PARAMS._replace(omega_coriolis=jnp.array([0.0, 0.0, 7.29e-5]))
    with pytest.raises(imu.ImuError, match="omega_coriolis"):
        imu.imu_jacobians(*one_args, one_pim, rotating)


def test_bias_random_walk_blocks():
    """The bias random-walk factor's closed-form blocks are $-I$ and $I$ of $b_j - b_i$, as its
    autodiff Jacobian."""
    from lieax.factorgraph import Var
    from lieax.factorgraph._factors import linearize_one

    biases = Var(jnp.zeros((2, 6)))
    factor = imu.bias_random_walk_factor(biases[[0]], biases[[1]], np.array([1.0]), 1e-3, 1e-4)
    b_i, b_j = np.random.default_rng(3).normal(size=(2, 6))
    value, blocks = linearize_one(factor, (b_i, b_j), None)
    auto_value, auto = value_and_jacobian(factor.residual, (0, 1))(b_i, b_j)
    np.testing.assert_allclose(value, b_j - b_i, rtol=1e-15)
    np.testing.assert_allclose(value, auto_value, rtol=1e-15)
    np.testing.assert_array_equal(blocks[0], -np.eye(6))
    np.testing.assert_array_equal(blocks[1], np.eye(6))
    np.testing.assert_array_equal(auto[0], blocks[0])
    np.testing.assert_array_equal(auto[1], blocks[1])


def test_factors_in_a_graph():
    """Three keyframes at rest, their poses known (priors): the solve recovers zero velocities
    and the biases the samples carry (at rest, with the attitude known, all six are observable),
    to the accuracy of the first-order bias correction from the zero bias they were integrated
    at (measured 3e-6; GTSAM's model alike)."""
    from lieax.factorgraph import Factor, FactorGraph, Var

    true_bias = np.array([0.03, -0.02, 0.05, 0.002, -0.001, 0.003])
    gyro = np.tile(true_bias[3:], (2, 100, 1))
    accel = np.tile(true_bias[:3] + [0.0, 0.0, 9.81], (2, 100, 1))
    pim = jax.vmap(imu.preintegrate, in_axes=(0, 0, None, None, None))(
        gyro, accel, 0.01, np.zeros(6), PARAMS
    )
    start = SE3.exp(jnp.asarray(0.01 * np.random.default_rng(8).normal(size=(3, 6))))
    poses, velocities = Var(start, name="poses"), Var(jnp.full((3, 3), 0.1), name="velocities")
    biases = Var(jnp.zeros((3, 6)), name="biases")
    i, j = np.arange(2), np.arange(1, 3)
    graph = FactorGraph([
        imu.imu_factor(pim, PARAMS, poses[i], velocities[i], poses[j], velocities[j], biases[i]),
        imu.bias_random_walk_factor(biases[i], biases[j], np.asarray(pim.delta_t), 1e-3, 1e-4),
        Factor(lambda x: x.log(), (poses[np.arange(3)],), sqrt_information=1e4 * np.eye(6)),
    ])  # fmt: skip
    result = graph.solve()
    assert result.converged
    _, solved_velocities, solved_biases = result.values
    np.testing.assert_allclose(solved_velocities, 0.0, atol=2e-5)
    np.testing.assert_allclose(solved_biases, np.tile(true_bias, (3, 1)), atol=2e-5)


def test_imu_factor_rejects_invalid_intervals():
    from lieax.factorgraph import Var

    gyro, accel, dt = stream(9, samples=4)
    bad = np.array(dt)
    bad[0] = -1.0
    pim = jax.vmap(imu.preintegrate, in_axes=(0, 0, 0, None, None))(
        np.stack([gyro, gyro]), np.stack([accel, accel]), np.stack([dt, bad]), BIAS, PARAMS
    )
    poses, vectors = Var(SE3.identity((2,))), Var(jnp.zeros((2, 3)))
    biases = Var(jnp.zeros((2, 6)))
    index = np.array([0, 0])
    with pytest.raises(imu.ImuError, match="pim 1 is invalid"):
        imu.imu_factor(
            pim, PARAMS, poses[index], vectors[index], poses[index], vectors[index], biases[index]
        )
    with pytest.raises(imu.ImuError, match="delta_t"):
        imu.bias_random_walk_factor(biases[index], biases[index], np.array([1.0, 0.0]), 1e-3, 1e-4)
