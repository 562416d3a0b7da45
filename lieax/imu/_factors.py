r"""IMU factors for `lieax.factorgraph`: the preintegrated IMU factor between
$(T_i, v_i, T_j, v_j, b_i)$ and the bias random walk between $(b_i, b_j)$.

The states are an `SE3` pose $T_{nb}$ and a navigation-frame velocity in $\mathbb{R}^3$ (GTSAM's
`ImuFactor` / `CombinedImuFactor` variables, so graphs and Jacobians map one to one), biases
$(b_a, b_g) \in \mathbb{R}^6$. The residual is GTSAM's `ImuFactorErrorMode.ComponentWise`
error, the prediction in the local coordinates of $x_j$ (`PreintegrationBase::computeError`):
$r = (\mathrm{Log}(R_j^\top \hat R_j),\ R_j^\top(\hat p_j - p_j),\ R_j^\top(\hat v_j - v_j))$
with $(\hat T_j, \hat v_j)$ = `predict`, whitened by `Preintegrated.residual_covariance` (the
preintegrated covariance mapped into the residual's coordinates, as GTSAM 4.3's `ImuFactor`).
Jacobians come from the groups' closed-form rules through `lieax.value_and_jacobian`.
Conventions: the README's "Conventions"; GTSAM's mapping in `lieax.conventions`.
"""

import jax
import jax.numpy as jnp
import numpy as np

from ..factorgraph._factors import Factor
from ._preintegration import ImuError, ImuParams, Preintegrated, predict


def imu_residual(pose_i, velocity_i, pose_j, velocity_j, bias_i, pim: Preintegrated, params):
    r"""The unwhitened 9-vector $(r_\theta, r_p, r_v)$ of one IMU factor (module docstring):
    `pose_i`, `pose_j` `SE3` ($T_{nb}$), velocities `(3,)`, `bias_i` `(6,)`, `pim` one interval."""
    pose_hat, velocity_hat = predict(pim, pose_i, velocity_i, bias_i, params)
    rotation_j = pose_j.rotation()
    r_theta = rotation_j.between(pose_hat.rotation()).log()
    r_p = rotation_j.inverse() @ (pose_hat.translation() - pose_j.translation())
    r_v = rotation_j.inverse() @ (velocity_hat - velocity_j)
    return jnp.concatenate([r_theta, r_p, r_v])


def imu_factor(
    pim: Preintegrated, params: ImuParams, pose_i, velocity_i, pose_j, velocity_j, bias_i
):
    r"""A `Factor` kind of IMU factors, one per interval of the batched `pim` (`(m,)`).

    **Arguments:**
    - `pim`: a `Preintegrated` batched `(m,)` (e.g. `vmap(preintegrate)` over intervals).
    - `params`: the `ImuParams` they were integrated with (for gravity).
    - `pose_i`, `velocity_i`, `pose_j`, `velocity_j`, `bias_i`: `var[index]` references, index
      arrays `(m,)` (poses an `SE3` `Var`, velocities `(n, 3)`, biases `(n, 6)`).

    **Returns:** a `Factor` with information $\Sigma_r^{-1}$, $\Sigma_r$ each interval's
    `residual_covariance()`.
    Raises `ImuError` when a `pim` is invalid or its covariance is not positive definite.
    """
    valid = np.asarray(pim.valid)
    if valid.ndim != 1:
        raise ImuError(
            f"pim must be batched over intervals (m,), got valid of shape {valid.shape}."
        )
    if not valid.all():
        raise ImuError(f"pim {int(np.flatnonzero(~valid)[0])} is invalid (bad samples).")
    covariance = np.asarray(pim.residual_covariance())
    try:
        information = np.linalg.inv(covariance)
        information = 0.5 * (information + np.swapaxes(information, 1, 2))
        return Factor(
            lambda xi, vi, xj, vj, bi, data: imu_residual(xi, vi, xj, vj, bi, data, params),
            (pose_i, velocity_i, pose_j, velocity_j, bias_i),
            pim,
            information=information,
            name="imu",
        )
    except (np.linalg.LinAlgError, ValueError) as error:
        raise ImuError(f"IMU factor: the preintegrated covariance is singular ({error}).") from None


def bias_random_walk_factor(bias_i, bias_j, delta_t, accel_bias_sigma, gyro_bias_sigma):
    r"""A `Factor` kind $r = b_j - b_i$ with covariance
    $\Delta t\,\mathrm{diag}(\sigma_{b_a}^2 I, \sigma_{b_g}^2 I)$: the bias random walk of
    GTSAM's `CombinedImuFactor` (`biasAccCovariance`, `biasOmegaCovariance`, continuous time),
    without its coupling of the bias noise into the navigation covariance (as
    `ImuFactor` + `BetweenFactor<ConstantBias>`).

    **Arguments:** `bias_i`, `bias_j` `var[index]` references (index arrays `(m,)`), `delta_t`
    `(m,)` the intervals' durations, the random-walk sigmas (m/s³/√Hz, rad/s²/√Hz).
    """
    delta_t = np.asarray(delta_t, dtype=np.float64)
    if delta_t.ndim != 1 or not np.all(np.isfinite(delta_t)) or not np.all(delta_t > 0):
        raise ImuError(f"delta_t must be positive and finite, shape (m,), got {delta_t.shape}.")
    if not (accel_bias_sigma > 0 and gyro_bias_sigma > 0):
        raise ImuError("the bias random-walk sigmas must be positive.")
    sigmas = np.repeat([accel_bias_sigma, gyro_bias_sigma], 3)
    sqrt_information = jax.vmap(jnp.diag)(1.0 / (sigmas[None] * np.sqrt(delta_t)[:, None]))
    return Factor(
        lambda bi, bj: bj - bi,
        (bias_i, bias_j),
        sqrt_information=np.asarray(sqrt_information),
        name="bias_random_walk",
    )
