r"""The parameters of IMU preintegration (GTSAM 4.3's `PreintegrationParams` and
`PreintegrationCombinedParams`): the noise densities, gravity, the sensor's pose in the body frame
and the navigation frame's rotation rate (`ImuParams`), the biases' random walk
(`BiasRandomWalk`), their checks, and the error that bad samples, parameters or biases raise
(`ImuError`). Conventions: docs/conventions.md.
"""

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from .._checks import to_device
from ..groups import SE3


class ImuError(ValueError):
    """Bad IMU samples, parameters or biases (shapes, non-finite values, non-positive `dt`)."""


class ImuParams(NamedTuple):
    r"""Preintegration parameters (GTSAM's `PreintegrationParams`), a pytree.

    **Fields:**

    - `accelerometer_covariance`: $\Sigma_a$, `(3, 3)`, continuous time
      ((m/s²)²/Hz, the noise density squared; the discrete covariance is $\Sigma_a / \delta t$).
    - `gyroscope_covariance`: $\Sigma_g$, `(3, 3)`, (rad/s)²/Hz.
    - `integration_covariance`: $\Sigma_i$, `(3, 3)`, added to the position as $\Sigma_i\,\delta t$.
    - `n_gravity`: gravity in the navigation frame, `(3,)`.
    - `body_P_sensor`: the sensor's pose in the body frame (`SE3`), or `None` for the identity.
    - `omega_coriolis`: the navigation frame's rotation rate $\omega_c$ (rad/s, `(3,)`, e.g. the
      Earth's in a local-level frame), for `predict` in a rotating frame (Coriolis and
      centrifugal terms), or `None` for an inertial one (GTSAM's `omegaCoriolis`).
    """

    accelerometer_covariance: jax.Array
    gyroscope_covariance: jax.Array
    integration_covariance: jax.Array
    n_gravity: jax.Array
    body_P_sensor: SE3 | None = None
    omega_coriolis: jax.Array | None = None

    @classmethod
    def make_u(
        cls,
        gravity=9.81,
        *,
        accel_noise_density=0.0,
        gyro_noise_density=0.0,
        integration_sigma=0.0,
        body_P_sensor=None,
        omega_coriolis=None,
    ):
        r"""Z up, gravity along $-z$ (GTSAM's `PreintegrationParams.MakeSharedU(g)`), with isotropic
        covariances $\sigma^2 I$ from the noise densities (m/s²/√Hz, rad/s/√Hz) and the
        integration sigma."""
        eye = np.eye(3)
        return cls(
            to_device(accel_noise_density**2 * eye),  # transfers, no compiled conversion
            to_device(gyro_noise_density**2 * eye),
            to_device(integration_sigma**2 * eye),
            to_device(np.array([0.0, 0.0, -float(gravity)])),
            body_P_sensor,
            None if omega_coriolis is None else jnp.asarray(omega_coriolis, dtype=float),
        )


class BiasRandomWalk(NamedTuple):
    r"""The biases' random walk for `preintegrate_combined` (GTSAM 4.3's
    `PreintegrationCombinedParams`), a pytree.

    **Fields:**

    - `accelerometer_bias_covariance`: `(3, 3)`, continuous time ((m/s³)²/Hz; `biasAccCovariance`).
    - `gyroscope_bias_covariance`: `(3, 3)`, (rad/s²)²/Hz (`biasOmegaCovariance`).
    """

    accelerometer_bias_covariance: jax.Array
    gyroscope_bias_covariance: jax.Array

    @classmethod
    def isotropic(cls, accel_bias_sigma, gyro_bias_sigma):
        r"""$\sigma^2 I$ from the random-walk densities (m/s³/√Hz, rad/s²/√Hz)."""
        eye = np.eye(3)
        return cls(jnp.asarray(accel_bias_sigma**2 * eye), jnp.asarray(gyro_bias_sigma**2 * eye))


def _check_params(params):
    if not isinstance(params, ImuParams):
        raise TypeError(f"params must be an ImuParams, got {type(params).__name__}.")
    for name in ("accelerometer_covariance", "gyroscope_covariance", "integration_covariance"):
        if jnp.shape(getattr(params, name)) != (3, 3):
            raise ImuError(f"params.{name} must be (3, 3), got {jnp.shape(getattr(params, name))}.")
    if jnp.shape(params.n_gravity) != (3,):
        raise ImuError(f"params.n_gravity must be (3,), got {jnp.shape(params.n_gravity)}.")
    if params.body_P_sensor is not None and not isinstance(params.body_P_sensor, SE3):
        raise TypeError("params.body_P_sensor must be an SE3 or None.")
    if params.omega_coriolis is not None and jnp.shape(params.omega_coriolis) != (3,):
        raise ImuError(
            f"params.omega_coriolis must be (3,) or None, got {jnp.shape(params.omega_coriolis)}."
        )
