"""Inertial navigation: IMU preintegration (Forster et al., T-RO 2017; GTSAM's
`PreintegratedImuMeasurements`), its bias-corrected prediction, and IMU and bias random-walk
factors for `lieax.factorgraph`. `combined_imu_factor` joins the IMU factor and the bias random
walk of one interval in one factor whitened by `preintegrate_combined`'s 15×15 covariance
(GTSAM's `CombinedImuFactor`). Conventions: the README's "Conventions"; the mapping to GTSAM's
is in `lieax.conventions`.
"""

from ._factors import (
    bias_random_walk_factor,
    combined_imu_factor,
    combined_imu_jacobians,
    combined_imu_residual,
    imu_factor,
    imu_jacobians,
    imu_residual,
)
from ._preintegration import (
    BiasRandomWalk,
    ImuError,
    ImuParams,
    Preintegrated,
    predict,
    preintegrate,
    preintegrate_associative,
    preintegrate_combined,
)

__all__ = [
    "BiasRandomWalk",
    "ImuError",
    "ImuParams",
    "Preintegrated",
    "bias_random_walk_factor",
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
]
