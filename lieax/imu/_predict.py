r"""`predict`: the state at keyframe $j$ from the state at $i$ and the preintegrated increments,
in an inertial or a rotating navigation frame (GTSAM 4.3's `NavState::predictPIM`).
Conventions: docs/conventions.md.
"""

import jax.numpy as jnp

from .._linalg import cross, dot, skew
from ..groups import SE3, SO3, kernels
from ._params import ImuParams
from ._preintegrated import Preintegrated


def predict(pim: Preintegrated, pose_i: SE3, velocity_i, bias, params: ImuParams):
    r"""The state at $j$ from the state at $i$ (GTSAM 4.3's `PreintegrationBase::predict`,
    `NavState::predictPIM`): with $(\theta, \Delta p, \Delta v)$ = `pim.bias_corrected(bias)`
    and $\Delta t$ = `pim.delta_t`, in an inertial frame (`params.omega_coriolis` `None`)
    $R_j = R_i \mathrm{Exp}(\theta)$, $p_j = p_i + R_i \Delta p + v_i \Delta t + \tfrac12 g
    \Delta t^2$, $v_j = v_i + R_i \Delta v + g \Delta t$.

    In a frame rotating at $\omega_c$ (Brossard, Barrau, Chauchat and Bonnabel, "Associating
    uncertainty to extended poses for on Lie group IMU preintegration with rotating Earth",
    T-RO 2022; GTSAM's `PIMPredictionRotating`): with the transported velocity
    $\bar v_i = v_i + \omega_c\times p_i$, $\phi = -\omega_c\Delta t$, $A = \mathrm{Exp}(\phi)$,
    $\Gamma_v = J_l(\phi) = I + g_2[\phi]_\times + g_3[\phi]_\times^2$ and $\Gamma_p = J_l(\phi) -
    \Gamma_2(\phi) = \tfrac12 I + (g_2 - g_3)[\phi]_\times + (g_3 - g_4)[\phi]_\times^2$
    ($\Gamma_2 = \sum_k [\phi]_\times^k/(k+2)!$, $g_n$ of `lieax.groups._series`):
    $R_j = A R_i \mathrm{Exp}(\theta)$, $p_j = A(p_i + \bar v_i\Delta t + R_i\Delta p) +
    \Gamma_p g\Delta t^2$, $v_j = A(\bar v_i + R_i\Delta v) + \Gamma_v g\Delta t - \omega_c\times
    p_j$: exact for a constant $\omega_c$ (Coriolis and centrifugal terms to all orders; GTSAM 4.3
    ignores `use2ndOrderCoriolis` likewise), equal to the inertial prediction at $\omega_c = 0$.

    **Arguments:** `pim` (one interval), `pose_i` ($T_{nb}$, `SE3`), `velocity_i` (navigation
    frame, `(3,)`), `bias` `(6,)`, `params` (`n_gravity`, `omega_coriolis`).

    **Returns:** `(pose_j, velocity_j)`.
    """
    corrected = pim.bias_corrected(bias)
    rotation_i, t = pose_i.rotation(), pim.delta_t
    gravity, position_i = params.n_gravity, pose_i.translation()
    rotation_z = rotation_i @ SO3.exp(corrected[:3])
    if params.omega_coriolis is None:
        position = position_i + rotation_i @ corrected[3:6] + velocity_i * t + 0.5 * gravity * t**2
        velocity = velocity_i + rotation_i @ corrected[6:] + gravity * t
        return SE3.from_rotation_and_translation(rotation_z, position), velocity
    omega = params.omega_coriolis
    phi = -omega * t
    s, w = dot(phi, phi), skew(phi)
    w2 = w @ w
    eye = jnp.eye(3, dtype=phi.dtype)
    gamma_v = eye + kernels.g(2, s) * w + kernels.g(3, s) * w2
    gamma_p = (
        0.5 * eye
        + (kernels.g(2, s) - kernels.g(3, s)) * w
        + (kernels.g(3, s) - kernels.g(4, s)) * w2
    )
    earth = SO3.exp(phi)
    transported = velocity_i + cross(omega, position_i)
    position_z = position_i + transported * t + rotation_i @ corrected[3:6]
    velocity_z = transported + rotation_i @ corrected[6:]
    position = earth @ position_z + gamma_p @ gravity * t**2
    velocity = earth @ velocity_z + gamma_v @ gravity * t - cross(omega, position)
    return SE3.from_rotation_and_translation(earth @ rotation_z, position), velocity
