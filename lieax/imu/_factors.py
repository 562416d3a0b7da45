r"""IMU factors for `lieax.factorgraph`: the preintegrated IMU factor between
$(T_i, v_i, T_j, v_j, b_i)$, the bias random walk between $(b_i, b_j)$, and the combined IMU
factor over $(T_i, v_i, T_j, v_j, b_i, b_j)$ that stacks the two and whitens them with
`preintegrate_combined`'s 15×15 covariance (GTSAM's `CombinedImuFactor`).

The states are an `SE3` pose $T_{nb}$ and a navigation-frame velocity in $\mathbb{R}^3$ (GTSAM's
`ImuFactor` / `CombinedImuFactor` variables, so graphs and Jacobians map one to one), biases
$(b_a, b_g) \in \mathbb{R}^6$. With $(\hat T_j, \hat v_j)$ = `predict` and
$x = (R, p, v) \in SE_2(3)$ (GTSAM's `NavState`), the prediction error is
$E = x_j^{-1}\hat x_j = (R_j^\top\hat R_j,\ c_p,\ c_v)$, $c_p = R_j^\top(\hat p_j - p_j)$,
$c_v = R_j^\top(\hat v_j - v_j)$, $c_\theta = \mathrm{Log}(R_j^\top\hat R_j)$, and the residual
is one of GTSAM 4.3's two `ImuFactorErrorMode`s (`error_mode=`):

- `"logmap"` (the default, as GTSAM 4.3's default for fresh `PreintegrationParams` and
  `PreintegrationCombinedParams`): $r = \mathrm{Log}_{SE_2(3)}(E) = (c_\theta,\ J_l^{-1}(c_\theta)
  c_p,\ J_l^{-1}(c_\theta) c_v)$ (`NavState::Logmap`, rotation first);
- `"component_wise"` (GTSAM's `ImuFactorErrorMode.ComponentWise`, lieax's only residual before
  2026-12): $r = (c_\theta,\ c_p,\ c_v)$.

The two agree in $r_\theta$ and to first order at $r = 0$ ($J_l^{-1}(c_\theta) = I +
O(c_\theta)$), so both are whitened by the same covariance, `Preintegrated.residual_covariance`
(GTSAM 4.3's `residualCovariance()`, which its factors install in either mode); away from zero
the position and velocity rows differ by $(J_l^{-1}(c_\theta) - I)(c_p, c_v)$, second order in
the residual (on GTSAM's KITTI example, issue 32 found 5.8e-6 relative in the final cost and
0.12 mm in position between the two). The factor's Jacobian blocks are closed forms (`imu_jacobians`); `imu_residual` itself
differentiates through the groups' rules (`lieax.value_and_jacobian`; the logmap residual through
`SE23`), which the tests compare. Conventions: docs/conventions.md; GTSAM's mapping in
`lieax.conventions`.
"""

from typing import NamedTuple

import jax
import jax.numpy as jnp
import numpy as np

from .._linalg import cross, dot, skew
from ..factorgraph import Factor, square_root_information
from ..groups import SE23, SO3, kernels
from ._params import ImuError, ImuParams
from ._predict import predict
from ._preintegrated import Preintegrated

ERROR_MODES = ("logmap", "component_wise")


def _check_error_mode(error_mode):
    if error_mode not in ERROR_MODES:
        raise ImuError(
            f"error_mode must be 'logmap' (GTSAM's ImuFactorErrorMode.Logmap, the default) or "
            f"'component_wise' (ImuFactorErrorMode.ComponentWise), got {error_mode!r}."
        )


def imu_residual(
    pose_i,
    velocity_i,
    pose_j,
    velocity_j,
    bias_i,
    pim: Preintegrated,
    params,
    *,
    error_mode="logmap",
):
    r"""The unwhitened 9-vector $(r_\theta, r_p, r_v)$ of one IMU factor (module docstring):
    `pose_i`, `pose_j` `SE3` ($T_{nb}$), velocities `(3,)`, `bias_i` `(6,)`, `pim` one interval,
    `error_mode` `"logmap"` (GTSAM 4.3's default) or `"component_wise"`.
    `"logmap"` is $\mathrm{Log}$ of `SE23`'s $x_j^{-1}\hat x_j$ with $\hat x_j$ = `predict`'s,
    reordered to rotation first; `"component_wise"` in an inertial frame is `_prediction_error`'s
    (the fused SO3 kernels `imu_jacobians` uses), with `params.omega_coriolis` `predict`'s
    rotating-frame prediction."""
    _check_error_mode(error_mode)
    coriolis = getattr(params, "omega_coriolis", None) is not None
    if error_mode == "component_wise" and not coriolis:
        return _prediction_error(pose_i, velocity_i, pose_j, velocity_j, bias_i, pim, params)[0]
    pose_hat, velocity_hat = predict(pim, pose_i, velocity_i, bias_i, params)
    if error_mode == "logmap":
        state_j = SE23.from_pose_and_velocity(pose_j, velocity_j)
        xi = state_j.between(SE23.from_pose_and_velocity(pose_hat, velocity_hat)).log()
        return jnp.concatenate([xi[..., 3:6], xi[..., 0:3], xi[..., 6:9]], axis=-1)
    rotation_j = pose_j.rotation()
    r_theta = rotation_j.between(pose_hat.rotation()).log()
    r_p = rotation_j.inverse() @ (pose_hat.translation() - pose_j.translation())
    r_v = rotation_j.inverse() @ (velocity_hat - velocity_j)
    return jnp.concatenate([r_theta, r_p, r_v])


class _Error(NamedTuple):
    """What `imu_jacobians` reuses of `_prediction_error`: the bias-corrected increments, the
    rotation matrices $R_i$, $R_j$, $R_c$, $J_r(\theta_c)$, $J_r^{-1}(r_\theta)$ and
    $r_p$, $r_v$."""

    dp_c: jax.Array
    dv_c: jax.Array
    ri: jax.Array
    rj: jax.Array
    rc: jax.Array
    jr_c: jax.Array
    jr_inv: jax.Array
    r_p: jax.Array
    r_v: jax.Array


def _prediction_error(pose_i, velocity_i, pose_j, velocity_j, bias_i, pim, params):
    r"""`(r, _Error)`: the inertial-frame residual (module docstring) with
    $R_c = \mathrm{Exp}(\theta_c)$ and $J_r(\theta_c)$ from `SO3.exp_and_right_jacobian`, and
    $r_\theta = \mathrm{Log}(R_j^\top R_i R_c)$ and $J_r^{-1}(r_\theta)$ from
    `SO3.log_and_right_jacobian_inverse` (one sine, cosine and arctangent in all); $\hat p_j$,
    $\hat v_j$ as `predict`. Differentiable through the groups' rules."""
    corrected = pim.bias_corrected(bias_i)
    theta_c, dp_c, dv_c = corrected[:3], corrected[3:6], corrected[6:]
    rotation_c, jr_c = SO3.exp_and_right_jacobian(theta_c)
    rotation_i, rotation_j = pose_i.rotation(), pose_j.rotation()
    r_theta, jr_inv = rotation_j.between(rotation_i @ rotation_c).log_and_right_jacobian_inverse()
    ri, rj, rc = rotation_i.as_matrix(), rotation_j.as_matrix(), rotation_c.as_matrix()
    t, g = pim.delta_t, params.n_gravity
    ri_dp, ri_dv = jnp.stack([dp_c, dv_c]) @ ri.T  # R_i x as xᵀ R_iᵀ
    position_hat = pose_i.translation() + ri_dp + velocity_i * t + 0.5 * g * t**2
    velocity_hat = velocity_i + ri_dv + g * t
    r_p, r_v = (
        jnp.stack([position_hat - pose_j.translation(), velocity_hat - velocity_j]) @ rj
    )  # R_jᵀ x
    residual = jnp.concatenate([r_theta, r_p, r_v])
    return residual, _Error(dp_c, dv_c, ri, rj, rc, jr_c, jr_inv, r_p, r_v)


def imu_jacobians(
    pose_i,
    velocity_i,
    pose_j,
    velocity_j,
    bias_i,
    pim: Preintegrated,
    params,
    *,
    error_mode="logmap",
):
    r"""`(r, (J_pose_i, J_velocity_i, J_pose_j, J_velocity_j, J_bias_i))`: `imu_residual` and its
    blocks `(9, 6)`, `(9, 3)`, `(9, 6)`, `(9, 3)`, `(9, 6)` in right-local tangents (poses
    $(\rho, \phi)$ with $T \oplus \delta = T\,\mathrm{Exp}(\delta)$, vectors additive), for
    `error_mode` `"logmap"` (the default) or `"component_wise"` (module docstring).

    The component-wise blocks: with $(\theta_c, \Delta p_c, \Delta v_c) = (\theta, \Delta p, \Delta v) + J_b(b_i - \hat b)$
    (`bias_corrected`), $R_c = \mathrm{Exp}(\theta_c)$, $E = R_j^\top R_i R_c$,
    $r_\theta = \mathrm{Log}(E)$, $Q = R_j^\top R_i$ and $J_b = [J_\theta; J_p; J_v]$ by rows:
    $$\frac{\partial r}{\partial T_i} = \begin{bmatrix} 0 & J_r^{-1}(r_\theta) R_c^\top \\
    Q & -Q[\Delta p_c]_\times \\ 0 & -Q[\Delta v_c]_\times \end{bmatrix},\quad
    \frac{\partial r}{\partial v_i} = \begin{bmatrix} 0 \\ R_j^\top\Delta t \\ R_j^\top
    \end{bmatrix},\quad
    \frac{\partial r}{\partial T_j} = \begin{bmatrix} 0 & -J_r^{-1}(r_\theta) E^\top \\
    -I & [r_p]_\times \\ 0 & [r_v]_\times \end{bmatrix},\quad
    \frac{\partial r}{\partial v_j} = \begin{bmatrix} 0 \\ 0 \\ -R_j^\top \end{bmatrix},\quad
    \frac{\partial r}{\partial b_i} = \begin{bmatrix} J_r^{-1}(r_\theta) J_r(\theta_c) J_\theta
    \\ Q J_p \\ Q J_v \end{bmatrix}.$$
    Derivation: $R_i\mathrm{Exp}(\phi)R_c = R_iR_c\mathrm{Exp}(R_c^\top\phi)$,
    $\mathrm{Exp}(-\phi)E = E\,\mathrm{Exp}(-E^\top\phi)$,
    $\mathrm{Exp}(\theta_c + \delta) \approx \mathrm{Exp}(\theta_c)\mathrm{Exp}(J_r(\theta_c)\delta)$
    and $\mathrm{Log}(E\,\mathrm{Exp}(\delta)) \approx r_\theta + J_r^{-1}(r_\theta)\delta$;
    $p_i + R_i\rho$, $R_i\mathrm{Exp}(\phi)x \approx R_i x - R_i[x]_\times\phi$, and
    $\mathrm{Exp}(-\phi)R_j^\top y \approx R_j^\top y + [R_j^\top y]_\times\phi$. Forster et al.,
    T-RO 2017, Appendix (eqs. for $r_{\Delta R}, r_{\Delta v}, r_{\Delta p}$), in GTSAM's
    ComponentWise form: `PreintegrationBase::computeErrorAndJacobians` with
    `TangentPreintegration::biasCorrectedDelta` (GTSAM 4.3), whose blocks these equal (after
    `lieax.conventions`' column permutation of the poses; `tests/test_imu.py`). In an inertial
    navigation frame only: `ImuError` when `params.omega_coriolis` is set (`imu_factor` then
    differentiates `imu_residual`).

    The logmap blocks are these premultiplied by the derivative of $(c_\theta, c_p, c_v) \mapsto
    (c_\theta, J_l^{-1}(c_\theta)c_p, J_l^{-1}(c_\theta)c_v)$ (`_logmap_from_component_wise`).
    """
    _check_error_mode(error_mode)
    if getattr(params, "omega_coriolis", None) is not None:
        raise ImuError("imu_jacobians: the closed form is for params.omega_coriolis None.")
    residual, e = _prediction_error(pose_i, velocity_i, pose_j, velocity_j, bias_i, pim, params)
    rj_t = e.rj.T
    q = rj_t @ e.ri
    jac_b = pim.jacobian_bias
    # few, wider products (each product is one kernel of the vmapped program)
    jr_inv_rc_t, jr_inv_jr_c = _split(e.jr_inv @ jnp.concatenate([e.rc.T, e.jr_c], 1), 3)
    q_dp, q_dv, q_jp, q_jv = _split(
        q @ jnp.concatenate([skew(e.dp_c), skew(e.dv_c), jac_b[3:6], jac_b[6:9]], 1), 3, 6, 12
    )
    zero, eye = jnp.zeros((3, 3), q.dtype), jnp.eye(3, dtype=q.dtype)
    blocks = (
        jnp.block([[zero, jr_inv_rc_t], [q, -q_dp], [zero, -q_dv]]),
        jnp.concatenate([zero, rj_t * pim.delta_t, rj_t]),
        # E = Q R_c, so J_r^{-1} Eᵀ = (J_r^{-1} R_cᵀ) Qᵀ
        jnp.block([[zero, -jr_inv_rc_t @ q.T], [-eye, skew(e.r_p)], [zero, skew(e.r_v)]]),
        jnp.concatenate([zero, zero, -rj_t]),
        jnp.concatenate([jr_inv_jr_c @ jac_b[0:3], q_jp, q_jv]),
    )
    if error_mode == "logmap":
        return _logmap_from_component_wise(residual, e.jr_inv, blocks)
    return residual, blocks


def _logmap_from_component_wise(residual, jr_inv, blocks):
    r"""The logmap residual and blocks from the component-wise ones $c = (c_\theta, c_p, c_v)$,
    $B$: $r = (c_\theta, J_l^{-1}c_p, J_l^{-1}c_v)$ with $J_l^{-1} = J_l^{-1}(c_\theta) =
    J_r^{-1}(c_\theta)^\top$ (`jr_inv` is $J_r^{-1}(c_\theta)$; $J_l(\omega) = J_r(-\omega) =
    J_r(\omega)^\top$), $\mathrm{Log}_{SE_2(3)}$ of $(\mathrm{Exp}(c_\theta), c_p, c_v)$ (Barrau and
    Bonnabel 2017; GTSAM's `NavState::Logmap`), and each block $D B$ with
    $D = [[I, 0, 0], [H(c_p), J_l^{-1}, 0], [H(c_v), 0, J_l^{-1}]]$,
    $H(u) = \partial(J_l^{-1}(\theta)u)/\partial\theta = \tfrac12[u]_\times + D_\theta((\theta\cdot u)I
    + \theta u^\top - 2u\theta^\top) + 2D_\theta'\,\theta\times(\theta\times u)\,\theta^\top$ from
    $J_l^{-1}(\theta) = I - \tfrac12[\theta]_\times + D_\theta[\theta]_\times^2$ (Solà eq. 146;
    $D_\theta$, $D_\theta' = dD/ds$ at $s = \theta\cdot\theta$ of
    `lieax.groups._so3.jr_inverse_coefficients`; `_so3_at` of `lieax.imu._block_scan` has
    the $J_r^{-1}$ twin)."""
    theta, c_p, c_v = residual[0:3], residual[3:6], residual[6:9]
    s = dot(theta, theta)
    half_cos, half_sinc, *_ = kernels.so3_exp_coefficients(s)
    d, d_prime = kernels.so3_jr_inverse_coefficients(s, half_cos, half_sinc)
    eye = jnp.eye(3, dtype=theta.dtype)
    jl_inv = jr_inv.T

    def h(u):
        return (
            0.5 * skew(u)
            + d * (dot(theta, u) * eye + jnp.outer(theta, u) - 2.0 * jnp.outer(u, theta))
            + 2.0 * d_prime * jnp.outer(cross(theta, cross(theta, u)), theta)
        )

    h_pv = jnp.concatenate([h(c_p), h(c_v)])  # (6, 3)
    value = jnp.concatenate([theta, jl_inv @ c_p, jl_inv @ c_v])

    def convert(block):
        moved = h_pv @ block[0:3]
        return jnp.concatenate(
            [block[0:3], moved[0:3] + jl_inv @ block[3:6], moved[3:6] + jl_inv @ block[6:9]]
        )

    return value, tuple(convert(b) for b in blocks)


def _split(matrix, *columns):
    """The column blocks of `matrix` split before each of `columns`."""
    return jnp.split(matrix, columns, axis=-1)


def _residual_coordinates_host(theta, bias_size=0):
    r"""`residual_coordinates` on the host, in NumPy (construction holds `theta` as data: no
    tracing, no compilation), `(m, 9 + bias_size, 9 + bias_size)`: $\Delta R = I + g_1 W +
    g_2 W^2$, $J_r = I - g_2 W + g_3 W^2$ ($W = [\theta]_\times$, Solà eqs. 77 and 143) with the
    coefficients of `lieax.groups._so3.exp_coefficients`."""
    theta = np.asarray(theta, dtype=np.float64)
    s = np.einsum("...i,...i->...", theta, theta)
    _, _, g1, g2, g3 = kernels.so3_exp_coefficients(s, np)
    x, y, z = theta[..., 0], theta[..., 1], theta[..., 2]
    zero = np.zeros_like(x)
    w = np.stack([np.stack(r, -1) for r in ((zero, -z, y), (z, zero, -x), (-y, x, zero))], -2)
    eye = np.eye(3)
    w2 = theta[..., :, None] * theta[..., None, :] - s[..., None, None] * eye
    rotation_t = np.swapaxes(eye + g1[..., None, None] * w + g2[..., None, None] * w2, -1, -2)
    size = 9 + bias_size
    m = np.zeros((*theta.shape[:-1], size, size))
    m[..., 0:3, 0:3] = eye - g2[..., None, None] * w + g3[..., None, None] * w2
    m[..., 3:6, 3:6] = m[..., 6:9, 6:9] = rotation_t
    m[..., 9:, 9:] = np.eye(bias_size)
    return m


def _residual_covariance(pim: Preintegrated):
    r"""`pim.residual_covariance()` on the host: $M \Sigma M^\top$,
    $M$ = `_residual_coordinates_host(theta)`, `(m, 9, 9)` NumPy."""
    m, covariance = _residual_coordinates_host(pim.theta), np.asarray(pim.covariance)
    return (m @ covariance @ np.swapaxes(m, -1, -2)).astype(covariance.dtype)


def imu_factor(
    pim: Preintegrated,
    params: ImuParams,
    pose_i,
    velocity_i,
    pose_j,
    velocity_j,
    bias_i,
    *,
    error_mode="logmap",
):
    r"""A `Factor` kind of IMU factors, one per interval of the batched `pim` (`(m,)`).

    **Arguments:**

    - `pim`: a `Preintegrated` batched `(m,)` (e.g. `vmap(preintegrate)` over intervals).
    - `params`: the `ImuParams` they were integrated with (for gravity).
    - `pose_i`, `velocity_i`, `pose_j`, `velocity_j`, `bias_i`: `var[index]` references, index
      arrays `(m,)` (poses an `SE3` `Var`, velocities `(n, 3)`, biases `(n, 6)`).
    - `error_mode`: `"logmap"` (default: GTSAM 4.3's default `ImuFactor`, whose residual is
      `NavState::Logmap` of $x_j^{-1}\hat x_j$) or `"component_wise"` (GTSAM's
      `ImuFactorErrorMode.ComponentWise`: rotation log, position and velocity differences in
      frame $j$); the module docstring gives both and their difference.

    **Returns:** a `Factor` with square-root information $L^{-1}$, $L L^\top = \Sigma_r$ the
    Cholesky factorization of each interval's `residual_covariance()` (`_sqrt_information`; the
    same in both modes, as GTSAM's), and the closed-form blocks of `imu_jacobians` (autodiff of
    `imu_residual` with `params.omega_coriolis`).
    Raises `ImuError` when a `pim` is invalid or its covariance is not positive definite.
    """
    _check_error_mode(error_mode)
    _check_intervals(pim)
    sqrt_information = _sqrt_information(
        np.asarray(_residual_covariance(pim)), "IMU factor: the 9x9"
    )
    mode = dict(error_mode=error_mode)
    return Factor(
        lambda xi, vi, xj, vj, bi, data: imu_residual(xi, vi, xj, vj, bi, data, params, **mode),
        (pose_i, velocity_i, pose_j, velocity_j, bias_i),
        pim,
        sqrt_information=sqrt_information,
        jacobian_fn=None
        if getattr(params, "omega_coriolis", None) is not None
        else lambda xi, vi, xj, vj, bi, data: imu_jacobians(
            xi, vi, xj, vj, bi, data, params, **mode
        ),
        name="imu",
    )


def _sqrt_information(covariance, what):
    r"""$L^{-1}$, `(m, n, n)`, for $L L^\top = \Sigma$ the Cholesky factorization of each
    covariance (`(m, n, n)`): `lieax.factorgraph`'s `square_root_information(covariance=True)`,
    the whitening $\|L^{-1} r\|^2 = r^\top\Sigma^{-1} r$ without forming $\Sigma^{-1}$.
    `ImuError` naming `what` and the first bad interval unless every one is finite, symmetric
    and positive definite."""
    try:
        return square_root_information(covariance, "interval", covariance=True)
    except ValueError as error:
        raise ImuError(f"{what} covariance is not positive definite: {error}") from None


def _check_intervals(pim):
    """The number of intervals `m` of a batched `pim`; `ImuError` unless every one is valid."""
    valid = np.asarray(pim.valid)
    if valid.ndim != 1:
        raise ImuError(
            f"pim must be batched over intervals (m,), got valid of shape {valid.shape}."
        )
    if not valid.all():
        raise ImuError(f"pim {int(np.flatnonzero(~valid)[0])} is invalid (bad samples).")
    return len(valid)


def combined_imu_residual(
    pose_i,
    velocity_i,
    pose_j,
    velocity_j,
    bias_i,
    bias_j,
    pim: Preintegrated,
    params,
    *,
    error_mode="logmap",
):
    r"""The unwhitened 15-vector $(r_\theta, r_p, r_v, b_j - b_i)$ of one combined IMU factor:
    `imu_residual` (in `error_mode`, as GTSAM's `CombinedImuFactor` follows its parameters'
    `ImuFactorErrorMode`) stacked with the bias random walk's $b_j - b_i$ (GTSAM's
    `CombinedImuFactor` has $b_i - b_j$; `lieax.conventions`)."""
    residual = imu_residual(
        pose_i, velocity_i, pose_j, velocity_j, bias_i, pim, params, error_mode=error_mode
    )
    return jnp.concatenate([residual, bias_j - bias_i])


def combined_imu_jacobians(
    pose_i,
    velocity_i,
    pose_j,
    velocity_j,
    bias_i,
    bias_j,
    pim: Preintegrated,
    params,
    *,
    error_mode="logmap",
):
    r"""`(r, (J_pose_i, J_velocity_i, J_pose_j, J_velocity_j, J_bias_i, J_bias_j))`:
    `combined_imu_residual` and its blocks `(15, 6)`, `(15, 3)`, `(15, 6)`, `(15, 3)`, `(15, 6)`,
    `(15, 6)`. The first nine rows are `imu_jacobians`' (no $b_j$ column: zero), the last six
    those of $b_j - b_i$:
    $$\frac{\partial r}{\partial b_i} = \begin{bmatrix} \partial r_{1:9} / \partial b_i \\ -I
    \end{bmatrix},\quad \frac{\partial r}{\partial b_j} = \begin{bmatrix} 0 \\ I \end{bmatrix},$$
    zero bias rows for the poses and velocities (GTSAM 4.3 `CombinedImuFactor::evaluateError`,
    its bias rows negated). `ImuError` when `params.omega_coriolis` is set, as `imu_jacobians`.
    """
    residual, blocks = imu_jacobians(
        pose_i, velocity_i, pose_j, velocity_j, bias_i, pim, params, error_mode=error_mode
    )
    dtype = residual.dtype
    eye = jnp.eye(6, dtype=dtype)

    def no_bias_rows(block):
        return jnp.concatenate([block, jnp.zeros((6, block.shape[1]), dtype)])

    *navigation, j_bias_i = blocks
    return jnp.concatenate([residual, bias_j - bias_i]), (
        *(no_bias_rows(b) for b in navigation),
        jnp.concatenate([j_bias_i, -eye]),
        jnp.concatenate([jnp.zeros((9, 6), dtype), eye]),
    )


def _combined_residual_covariance(pim: Preintegrated, covariance):
    r"""The covariance of `combined_imu_residual`, `(*batch, 15, 15)` NumPy, on the host:
    `preintegrate_combined`'s 15×15 `covariance` of $(\theta, \Delta p, \Delta v, b_a, b_g)$ as
    $M \Sigma M^\top$, $M$ = `residual_coordinates(theta, bias_size=6)`
    (`_residual_coordinates_host`; GTSAM 4.3's
    `PreintegratedCombinedMeasurements::residualCovariance()`, its `CombinedImuFactor`'s noise
    model, up to the sign of the bias rows)."""
    m, covariance = _residual_coordinates_host(pim.theta, bias_size=6), np.asarray(covariance)
    return (m @ covariance @ np.swapaxes(m, -1, -2)).astype(covariance.dtype)


def combined_imu_factor(
    pim: Preintegrated,
    covariance,
    params: ImuParams,
    pose_i,
    velocity_i,
    pose_j,
    velocity_j,
    bias_i,
    bias_j,
    *,
    error_mode="logmap",
):
    r"""A `Factor` kind of combined IMU factors (GTSAM 4.3's `CombinedImuFactor`), one per
    interval: `combined_imu_residual` over $(T_i, v_i, T_j, v_j, b_i, b_j)$, the IMU residual
    and the bias random walk in one 15-row factor whitened by the inverse square root of its
    15×15 covariance, which couples the two (`imu_factor` + `bias_random_walk_factor` treat
    them as independent). Between keyframes joined by it, no `bias_random_walk_factor`.

    **Arguments:**

    - `pim`, `covariance`: `vmap(preintegrate_combined)` over the intervals, a `Preintegrated`
      batched `(m,)` and its `(m, 15, 15)` covariance.
    - `params`: the `ImuParams` they were integrated with (for gravity).
    - `pose_i`, `velocity_i`, `pose_j`, `velocity_j`, `bias_i`, `bias_j`: `var[index]`
      references, index arrays `(m,)` (poses an `SE3` `Var`, velocities `(n, 3)`, biases
      `(n, 6)`).
    - `error_mode`: the navigation rows' residual, `"logmap"` (default, GTSAM 4.3's) or
      `"component_wise"`, as `imu_factor`'s.

    **Returns:** a `Factor` with square-root information $L^{-1}$, $L L^\top = \Sigma_r$ the
    Cholesky factorization of the residual's covariance $\Sigma_r = M \Sigma M^\top$
    (`_combined_residual_covariance`, `_sqrt_information`), and the closed-form blocks of
    `combined_imu_jacobians` (autodiff of `combined_imu_residual` with `params.omega_coriolis`).
    Raises `ImuError` when a `pim` is invalid, `covariance` is not `(m, 15, 15)`, or it is not
    positive definite (a zero bias random walk, for one).
    """
    _check_error_mode(error_mode)
    count = _check_intervals(pim)
    if np.shape(covariance) != (count, 15, 15):
        raise ImuError(
            f"covariance must be (m, 15, 15) = ({count}, 15, 15) (preintegrate_combined's), got "
            f"{np.shape(covariance)}."
        )
    sqrt_information = _sqrt_information(
        np.asarray(_combined_residual_covariance(pim, jnp.asarray(covariance))),
        "combined IMU factor: the 15x15",
    )
    coriolis = getattr(params, "omega_coriolis", None) is not None
    mode = dict(error_mode=error_mode)
    return Factor(
        lambda xi, vi, xj, vj, bi, bj, data: combined_imu_residual(
            xi, vi, xj, vj, bi, bj, data, params, **mode
        ),
        (pose_i, velocity_i, pose_j, velocity_j, bias_i, bias_j),
        pim,
        sqrt_information=sqrt_information,
        jacobian_fn=None
        if coriolis
        else lambda xi, vi, xj, vj, bi, bj, data: combined_imu_jacobians(
            xi, vi, xj, vj, bi, bj, data, params, **mode
        ),
        name="combined_imu",
    )


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
    sqrt_information = np.eye(6) / (sigmas[None] * np.sqrt(delta_t)[:, None])[:, :, None]
    return Factor(
        _bias_difference,
        (bias_i, bias_j),
        sqrt_information=sqrt_information,
        jacobian_fn=_bias_difference_jacobians,
        name="bias_random_walk",
    )


def _bias_difference(bias_i, bias_j):
    return bias_j - bias_i


def _bias_difference_jacobians(bias_i, bias_j):
    r"""$r = b_j - b_i$: blocks $-I$, $I$ (`(6, 6)`)."""
    eye = jnp.eye(bias_i.shape[-1], dtype=bias_i.dtype)
    return bias_j - bias_i, (-eye, eye)
