"""The IMU tests' sample streams and their GTSAM 4.3 set-up (`tests/test_imu.py`,
`tests/test_imu_preintegration.py`): random gyroscope and accelerometer samples, the noise, bias
and lever arm they are integrated with, and the same in GTSAM's parameters and poses."""

import jax
import jax.numpy as jnp
import numpy as np

import lieax.imu as imu
from lieax import SE3, SO3
from lieax.imu import _sequential

SAMPLES = 60
NOISE = dict(accel_noise_density=0.01, gyro_noise_density=1e-3, integration_sigma=1e-4)
ARM = SE3.from_rotation_and_translation(
    SO3.exp(jnp.array([0.1, 0.2, -0.3])), jnp.array([0.1, -0.05, 0.2])
)
BIAS = np.array([0.1, -0.2, 0.05, 0.01, -0.02, 0.03])


def stream(seed, samples=SAMPLES, rate_scale=1.0):
    """`(gyro, accel, dt)`: random rates (scaled by `rate_scale`), gravity plus random
    accelerations, steps of 5–7 ms."""
    rng = np.random.default_rng(seed)
    gyro = rate_scale * rng.normal(size=(samples, 3))
    accel = rng.normal(size=(samples, 3)) + np.array([0.0, 0.0, 9.81])
    dt = 0.005 + 0.002 * rng.random(samples)
    return gyro, accel, dt


def relative(a, b):
    return np.max(np.abs(np.asarray(a) - b)) / np.max(np.abs(b))


def gtsam_params(gtsam, cls, omega=None, with_arm=False, error_mode="logmap"):
    """`cls.MakeSharedU(9.81)` (`PreintegrationParams` or `PreintegrationCombinedParams`) with
    `NOISE`, the factors' error mode (lieax's `error_mode`: `"logmap"` is GTSAM's default, left as
    it is; `"component_wise"` is set), and optionally `omegaCoriolis` and the lever arm `ARM`."""
    p = cls.MakeSharedU(9.81)
    p.setAccelerometerCovariance(NOISE["accel_noise_density"] ** 2 * np.eye(3))
    p.setGyroscopeCovariance(NOISE["gyro_noise_density"] ** 2 * np.eye(3))
    p.setIntegrationCovariance(NOISE["integration_sigma"] ** 2 * np.eye(3))
    if error_mode == "component_wise":
        p.setImuFactorErrorMode(gtsam.ImuFactorErrorMode.ComponentWise)
    else:  # lieax's default is GTSAM's default
        assert p.getImuFactorErrorMode() == gtsam.ImuFactorErrorMode.Logmap
    if omega is not None:
        p.setOmegaCoriolis(omega)
    if with_arm:
        p.setBodyPSensor(gtsam_pose(ARM))
    return p


def gtsam_pose(pose):
    import gtsam

    return gtsam.Pose3(
        gtsam.Rot3(np.asarray(pose.rotation().as_matrix())), np.asarray(pose.translation())
    )


def gtsam_bias(bias):
    import gtsam

    return gtsam.imuBias.ConstantBias(bias[:3], bias[3:])


def integrate(pim, gyro, accel, dt):
    """GTSAM's loop over `integrateMeasurement` (accelerometer first); returns `pim`."""
    for k in range(len(dt)):
        pim.integrateMeasurement(accel[k], gyro[k], dt[k])
    return pim


def entrywise_over_intervals(monkeypatch, *args, **kwargs):
    """`vmap(preintegrate)` with the entrywise scan for any batch (`_dispatch_batched` chooses
    it for $2^{23}$ samples or more): a fresh `jit`, traced with the threshold at zero."""
    monkeypatch.setattr(_sequential, "_ENTRYWISE_MIN_SAMPLES", 0)
    try:
        return jax.jit(jax.vmap(imu.preintegrate, in_axes=(None, None)))(*args, **kwargs)
    finally:
        monkeypatch.undo()
