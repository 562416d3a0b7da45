r"""The result of IMU preintegration between two keyframes (`Preintegrated`): the increments,
their covariance and their first-order bias correction, and the Jacobian that maps them to the IMU
residual's coordinates (`residual_coordinates`).

Forster, Carlone, Dellaert and Scaramuzza, "On-Manifold Preintegration for Real-Time
Visual-Inertial Odometry", T-RO 2017; GTSAM 4.3's `PreintegratedImuMeasurements` (its default
backend is `TangentPreintegration`, which the installed Python `gtsam` uses: it exposes
`preintegrated()`). The preintegrated vector is $(\theta, \Delta p, \Delta v)$ with
$\Delta R = \mathrm{Exp}(\theta)$, all in the body frame at keyframe $i$; the covariance and the
bias Jacobians are in the same order (GTSAM's `preintMeasCov`, `preintegrated_H_biasAcc`,
`preintegrated_H_biasOmega`). Biases are 6-vectors $(b_a, b_g)$, GTSAM's
`imuBias.ConstantBias.vector()` order. Conventions: docs/conventions.md.
"""

from typing import NamedTuple

import jax
import jax.numpy as jnp

from .._linalg import matvec
from ..groups import SO3, kernels


def residual_coordinates(theta, bias_size=0):
    r"""The Jacobian $M$ of the IMU residual at zero residual with respect to the preintegrated
    $(\theta, \Delta p, \Delta v)$ and, for `bias_size=6`, the biases' change over the interval,
    `(*batch, 9 + bias_size, 9 + bias_size)`:
    $M = \mathrm{diag}(J_r(\theta), \Delta R^\top, \Delta R^\top, I_{bias\_size})$,
    $\Delta R = \mathrm{Exp}(\theta)$. The rotation error is
    $\mathrm{Log}(\mathrm{Exp}(\theta)^{-1}\mathrm{Exp}(\theta + \delta)) \approx
    J_r(\theta)\delta$; position and velocity errors are in frame $j$; the bias coordinates are
    the residual's $b_j - b_i$ as they are. A covariance $\Sigma$ of those coordinates maps to the
    residual's as $M \Sigma M^\top$: GTSAM 4.3's `PreintegratedImuMeasurements::residualCovariance`
    (9×9) and `PreintegratedCombinedMeasurements::residualCovariance` (15×15, whose $M$ ends in
    $-I_6$ for its $b_i - b_j$, so its navigation-bias cross blocks have the opposite sign)."""
    rotation_t = jnp.swapaxes(kernels.so3_as_matrix(kernels.so3_exp(theta)), -1, -2)
    size = 9 + bias_size
    m = jnp.zeros((*theta.shape[:-1], size, size), theta.dtype)
    m = m.at[..., 0:3, 0:3].set(kernels.so3_right_jacobian(theta))
    m = m.at[..., 3:6, 3:6].set(rotation_t).at[..., 6:9, 6:9].set(rotation_t)
    if bias_size:
        m = m.at[..., 9:, 9:].set(jnp.eye(bias_size, dtype=theta.dtype))
    return m


class Preintegrated(NamedTuple):
    r"""Preintegrated IMU measurements of one interval (or a batch of them), a pytree.

    **Fields:**

    - `theta`, `delta_p`, `delta_v`: the preintegrated vector $(\theta, \Delta p, \Delta v)$,
      each `(*batch, 3)`; $\Delta R = \mathrm{Exp}(\theta)$ (`delta_R`).
    - `delta_t`: $\Delta t_{ij}$, `(*batch,)`.
    - `covariance`: `(*batch, 9, 9)` in the order $(\theta, \Delta p, \Delta v)$ (`preintMeasCov`).
    - `jacobian_bias`: $\partial(\theta, \Delta p, \Delta v) / \partial(b_a, b_g)$, `(*batch, 9, 6)`
      (`[preintegrated_H_biasAcc, preintegrated_H_biasOmega]`).
    - `bias_hat`: the bias the samples were corrected with, `(*batch, 6)`.
    - `valid`: `False` where the samples were non-finite or a `dt` was not positive (found
      under tracing; every other field is then NaN).
    """

    theta: jax.Array
    delta_p: jax.Array
    delta_v: jax.Array
    delta_t: jax.Array
    covariance: jax.Array
    jacobian_bias: jax.Array
    bias_hat: jax.Array
    valid: jax.Array

    @property
    def delta_R(self) -> SO3:
        return SO3.exp(self.theta)

    @property
    def J_theta_bias_gyro(self) -> jax.Array:
        r"""$\partial\theta / \partial b_g$ (GTSAM `ManifoldPreintegration`'s `delRdelBiasOmega`
        to first order at small $\theta$)."""
        return self.jacobian_bias[..., 0:3, 3:6]

    @property
    def J_p_bias_acc(self) -> jax.Array:
        return self.jacobian_bias[..., 3:6, 0:3]

    @property
    def J_p_bias_gyro(self) -> jax.Array:
        return self.jacobian_bias[..., 3:6, 3:6]

    @property
    def J_v_bias_acc(self) -> jax.Array:
        return self.jacobian_bias[..., 6:9, 0:3]

    @property
    def J_v_bias_gyro(self) -> jax.Array:
        return self.jacobian_bias[..., 6:9, 3:6]

    def residual_covariance(self):
        r"""The covariance of the IMU factor's residual (`lieax.imu.imu_residual`), `(*batch, 9, 9)`:
        `covariance` pushed through the residual's Jacobian at zero residual, $M \Sigma M^\top$
        with $M$ = `residual_coordinates(theta)` (GTSAM 4.3's `residualCovariance()`, which its
        `ImuFactor` whitens with)."""
        m = residual_coordinates(self.theta)
        return m @ self.covariance @ jnp.swapaxes(m, -1, -2)

    def bias_corrected(self, bias):
        r"""$(\theta, \Delta p, \Delta v) + J_b (b - \hat b)$, `(*batch, 9)` (GTSAM's
        `biasCorrectedDelta`, first order in the bias change)."""
        vector = jnp.concatenate([self.theta, self.delta_p, self.delta_v], axis=-1)
        return vector + matvec(self.jacobian_bias, bias - self.bias_hat)


def _result(x, delta_t, cov, jac, bias, ok):
    nan = jnp.nan

    def mask(a):
        return jnp.where(ok, a, nan)

    return Preintegrated(
        mask(x[:3]), mask(x[3:6]), mask(x[6:]), mask(delta_t), mask(cov), mask(jac), bias, ok
    )
