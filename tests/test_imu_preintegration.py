"""IMU preintegration options (`lieax.imu`): the Coriolis terms of `predict` and of the IMU
factor, and `preintegrate_combined`'s 15×15 covariance with the bias random walk, against GTSAM
4.3 (`PreintegrationParams.setOmegaCoriolis`, `PreintegratedCombinedMeasurements`) on random
sample streams; bad input."""

import functools

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from _imu_streams import ARM, BIAS, NOISE, gtsam_params, gtsam_pose, integrate, relative, stream

import lieax.imu as imu
from lieax import SE3
from lieax import conventions as cv
from lieax.autodiff import value_and_jacobian

OMEGA = np.array([2e-3, -5e-3, 7.292e-3])  # rad/s: exaggerated so that the terms are visible
WALK_ACC, WALK_GYRO = np.diag([1e-4, 2e-4, 3e-4]), np.diag([1e-6, 2e-6, 3e-6])

sequential = jax.jit(imu.preintegrate)
combined = jax.jit(imu.preintegrate_combined)
predict = jax.jit(imu.predict)
MODES = ("logmap", "component_wise")  # GTSAM 4.3's default ImuFactorErrorMode first
residual_and_jacobians = {
    mode: jax.jit(
        value_and_jacobian(functools.partial(imu.imu_residual, error_mode=mode), (0, 1, 2, 3, 4))
    )
    for mode in MODES
}


def params(omega=None, with_arm=False):
    return imu.ImuParams.make_u(
        9.81, **NOISE, body_P_sensor=ARM if with_arm else None, omega_coriolis=omega
    )


def random_states(seed):
    rng = np.random.default_rng(seed)
    poses = SE3.exp(jnp.asarray(rng.normal(size=(2, 6)) * [30, 30, 30, 1, 1, 1]))
    velocities = 5.0 * rng.normal(size=(2, 3))
    return poses[0], velocities[0], poses[1], velocities[1], BIAS + 0.01 * rng.normal(size=6)


# ---- Coriolis -------------------------------------------------------------------------------------


@pytest.mark.parametrize("error_mode", MODES)
def test_coriolis_predict_and_factor_match_gtsam(error_mode):
    r"""`predict` with `omega_coriolis` as `PreintegrationBase::predict` with `omegaCoriolis`
    (`NavState::predictPIM` in a rotating frame), and the IMU factor's residual and five
    Jacobians as GTSAM's `ImuFactor.evaluateError` in the same error mode; far from the origin
    and moving fast, so that every term counts."""
    gtsam = pytest.importorskip("gtsam")
    gyro, accel, dt = stream(0)
    ours_params = params(OMEGA)
    reference = integrate(
        gtsam.PreintegratedImuMeasurements(
            gtsam_params(gtsam, gtsam.PreintegrationParams, OMEGA, error_mode=error_mode),
            gtsam.imuBias.ConstantBias(BIAS[:3], BIAS[3:]),
        ),
        gyro, accel, dt,
    )  # fmt: skip
    pim = sequential(ours_params, BIAS, accel=accel, gyro=gyro, dt=dt)
    pose_i, velocity_i, pose_j, velocity_j, bias_i = random_states(1)
    bias_g = gtsam.imuBias.ConstantBias(bias_i[:3], bias_i[3:])
    predicted = reference.predict(gtsam.NavState(gtsam_pose(pose_i), velocity_i), bias_g)
    pose_hat, velocity_hat = predict(pim, pose_i, velocity_i, bias_i, ours_params)
    assert relative(pose_hat.as_matrix(), predicted.pose().matrix()) < 1e-12
    assert relative(velocity_hat, predicted.velocity()) < 1e-12
    # The terms are there: without them the prediction is off by more than the tolerance.
    plain_pose, plain_velocity = predict(pim, pose_i, velocity_i, bias_i, params())
    assert relative(plain_velocity, predicted.velocity()) > 1e-6
    assert relative(plain_pose.as_matrix(), predicted.pose().matrix()) > 1e-6

    factor = gtsam.ImuFactor(1, 2, 3, 4, 5, reference)
    shapes = (6, 3, 6, 3, 6)
    h = [np.zeros((9, n), order="F") for n in shapes]
    error = factor.evaluateError(
        gtsam_pose(pose_i), velocity_i, gtsam_pose(pose_j), velocity_j, bias_g, *h
    )
    value, jacobians = residual_and_jacobians[error_mode](
        pose_i, velocity_i, pose_j, velocity_j, bias_i, pim, ours_params
    )
    assert relative(value, error) < 1e-12
    for k, (ours, theirs) in enumerate(zip(jacobians, h)):
        if k in (0, 2):
            theirs = np.asarray(cv.se3_jacobian_from_gtsam(theirs, rows=False))
        assert relative(ours, theirs) < 1e-9, k


def test_rotating_frame_prediction_is_continuous_at_zero_rate():
    r"""At $\omega_c = 0$ the rotating-frame prediction (through $\mathrm{Exp}$, $J_l$,
    $\Gamma_2$ at zero) is the inertial one, and at a tiny rate it moves by first order."""
    gyro, accel, dt = stream(2)
    pim = sequential(params(), BIAS, accel=accel, gyro=gyro, dt=dt)
    pose_i, velocity_i, *_ = random_states(3)
    inertial_pose, inertial_velocity = predict(pim, pose_i, velocity_i, BIAS, params())
    for rate, tolerance in ((0.0, 1e-15), (1e-9, 1e-6)):
        pose, velocity = predict(pim, pose_i, velocity_i, BIAS, params(rate * OMEGA / 1e-2))
        difference = relative(velocity, inertial_velocity)
        assert difference < tolerance
        assert relative(pose.as_matrix(), inertial_pose.as_matrix()) < tolerance
        if rate:
            assert difference > 0.0


# ---- CombinedImuFactor's covariance ---------------------------------------------------------------


@pytest.mark.parametrize("with_arm", [False, True])
def test_combined_covariance_matches_gtsam(with_arm):
    """The 15×15 `preintMeasCov()` of `PreintegratedCombinedMeasurements` with anisotropic bias
    random walks, every block (navigation, coupling, biases), with and without a lever arm; the
    increments and bias Jacobians are `preintegrate`'s."""
    gtsam = pytest.importorskip("gtsam")
    gyro, accel, dt = stream(4)
    g_params = gtsam_params(gtsam, gtsam.PreintegrationCombinedParams, with_arm=with_arm)
    g_params.setBiasAccCovariance(WALK_ACC)
    g_params.setBiasOmegaCovariance(WALK_GYRO)
    reference = integrate(
        gtsam.PreintegratedCombinedMeasurements(
            g_params, gtsam.imuBias.ConstantBias(BIAS[:3], BIAS[3:])
        ),
        gyro, accel, dt,
    )  # fmt: skip
    ours_params = params(with_arm=with_arm)
    walk = imu.BiasRandomWalk(WALK_ACC, WALK_GYRO)
    pim, covariance = combined(ours_params, walk, BIAS, accel=accel, gyro=gyro, dt=dt)
    expected = reference.preintMeasCov()
    assert covariance.shape == (15, 15)
    for rows in (slice(0, 9), slice(9, 15)):
        for columns in (slice(0, 9), slice(9, 15)):
            assert relative(covariance[rows, columns], expected[rows, columns]) < 1e-9
    np.testing.assert_array_equal(pim.covariance, covariance[:9, :9])
    plain = sequential(ours_params, BIAS, accel=accel, gyro=gyro, dt=dt)
    for field in ("theta", "delta_p", "delta_v", "jacobian_bias"):
        np.testing.assert_allclose(
            getattr(pim, field), getattr(plain, field), rtol=1e-13, atol=1e-15
        )
    # The random walk feeds the navigation block; without it, that block is `preintegrate`'s.
    assert relative(pim.covariance, plain.covariance) > 1e-3
    still = imu.BiasRandomWalk(np.zeros((3, 3)), np.zeros((3, 3)))
    _, still_covariance = combined(ours_params, still, BIAS, accel=accel, gyro=gyro, dt=dt)
    assert relative(still_covariance[:9, :9], plain.covariance) < 1e-13
    np.testing.assert_array_equal(still_covariance[9:], 0.0)


def test_combined_bias_block_is_the_random_walk_and_batches():
    """The bias block is the random walk alone, $\\Sigma_b\\,\\Delta t$; `vmap` over intervals
    equals one at a time."""
    streams = [stream(10 + k, samples=20) for k in range(2)]
    gyro, accel, dt = (np.stack(x) for x in zip(*streams))
    walk = imu.BiasRandomWalk.isotropic(3e-3, 2e-5)
    batched = jax.jit(jax.vmap(imu.preintegrate_combined, in_axes=(None, None, None)))
    pims, covariances = batched(params(), walk, BIAS, accel=accel, gyro=gyro, dt=dt)
    for k, (g, a, d) in enumerate(streams):
        _, one = combined(params(), walk, BIAS, accel=a, gyro=g, dt=d)
        np.testing.assert_allclose(covariances[k], one, rtol=1e-10, atol=1e-30)
        walk_block = np.diag(np.repeat([3e-3**2, 2e-5**2], 3)) * d.sum()
        np.testing.assert_allclose(one[9:, 9:], walk_block, rtol=1e-12)


def test_bad_options():
    gyro, accel, dt = stream(5, samples=8)
    with pytest.raises(imu.ImuError, match=r"params.omega_coriolis must be \(3,\)"):
        imu.preintegrate(params(np.zeros(2)), BIAS, accel=accel, gyro=gyro, dt=dt)
    with pytest.raises(TypeError, match="walk must be a BiasRandomWalk"):
        imu.preintegrate_combined(
            params(), (WALK_ACC, WALK_GYRO), BIAS, accel=accel, gyro=gyro, dt=dt
        )
    with pytest.raises(imu.ImuError, match=r"walk.gyroscope_bias_covariance must be \(3, 3\)"):
        imu.preintegrate_combined(
            params(), imu.BiasRandomWalk(WALK_ACC, np.zeros(3)), BIAS, accel=accel, gyro=gyro, dt=dt
        )
    bad = dt.copy()
    bad[2] = -1.0
    with pytest.raises(imu.ImuError, match="sample 2: dt <= 0"):
        imu.preintegrate_combined(
            params(), imu.BiasRandomWalk(WALK_ACC, WALK_GYRO), BIAS, accel=accel, gyro=gyro, dt=bad
        )
    _, covariance = jax.jit(imu.preintegrate_combined)(
        params(), imu.BiasRandomWalk(WALK_ACC, WALK_GYRO), BIAS, accel=accel, gyro=gyro, dt=bad
    )
    assert np.all(np.isnan(covariance))
