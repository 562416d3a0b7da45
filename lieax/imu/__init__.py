"""Inertial navigation: IMU preintegration (Forster et al., T-RO 2017; GTSAM's
`PreintegratedImuMeasurements`), its bias-corrected prediction, and IMU and bias random-walk
factors for `lieax.factorgraph`. `combined_imu_factor` joins the IMU factor and the bias random
walk of one interval in one factor whitened by `preintegrate_combined`'s 15×15 covariance
(GTSAM's `CombinedImuFactor`). Conventions: docs/conventions.md; the mapping to GTSAM's
is in `lieax.conventions`.

The samples are keyword arguments in GTSAM's `integrateMeasurement(measuredAcc, measuredOmega,
dt)` order: `preintegrate(params, bias, accel=..., gyro=..., dt=...)`, and for a stream whose
intervals hold different numbers of samples, `preintegrate_intervals(params, bias, accel=[...],
gyro=[...], dt=...)` (padded with masks to bucketed lengths: one compilation per bucket).
`imu_factor`'s residual is GTSAM 4.3's default `ImuFactorErrorMode.Logmap`
(`error_mode="component_wise"` for `ComponentWise`).
"""

from ._associative import preintegrate_associative
from ._combined import preintegrate_combined
from ._factors import (
    bias_random_walk_factor,
    combined_imu_factor,
    combined_imu_jacobians,
    combined_imu_residual,
    imu_factor,
    imu_jacobians,
    imu_residual,
)
from ._intervals import bucket_size, preintegrate_intervals
from ._params import BiasRandomWalk, ImuError, ImuParams
from ._predict import predict
from ._preintegrated import Preintegrated
from ._sequential import preintegrate

__all__ = [
    "BiasRandomWalk",
    "ImuError",
    "ImuParams",
    "Preintegrated",
    "bias_random_walk_factor",
    "bucket_size",
    "combined_imu_factor",
    "combined_imu_jacobians",
    "combined_imu_residual",
    "imu_factor",
    "imu_jacobians",
    "imu_residual",
    "predict",
    "preintegrate",
    "preintegrate_associative",
    "preintegrate_combined",
    "preintegrate_intervals",
]
