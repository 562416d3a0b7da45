r"""Converters between lieax's conventions and those of GTSAM, Ceres, ROS and SciPy.

lieax (see docs/conventions.md): right perturbation $X \oplus \xi = X\,\mathrm{Exp}(\xi)$;
quaternions wxyz; tangents translation first: SE3 $(v, \omega)$, Sim3 $(v, \omega, \sigma)$ with
$T = [e^\sigma R, t; 0, 1]$; S2 tangents in the smooth basis of `lieax.S2.basis`.

| other library | what differs | converters here |
|---|---|---|
| GTSAM `Pose3` | tangent $(\omega, v)$, rotation first (Jacobians `H` permuted alike) | `se3_tangent_to_gtsam`, `se3_tangent_from_gtsam`, `se3_jacobian_to_gtsam`, `se3_jacobian_from_gtsam` |
| GTSAM `Similarity3` | tangent $(\omega, v, \lambda)$; matrix $[R, t_g; 0, 1/s]$, i.e. $t_g = t / s$ | `sim3_tangent_*`, `sim3_jacobian_*`, `sim3_to_gtsam`, `sim3_from_gtsam` |
| GTSAM `NavState` (SE23) | tangent $(\delta R, \delta p, \delta v)$, rotation first; lieax's is $(\rho_p, \omega, \rho_v)$ (manif's `SE_2_3`) | `se23_tangent_to_gtsam`, `se23_tangent_from_gtsam`, `se23_jacobian_to_gtsam`, `se23_jacobian_from_gtsam` |
| GTSAM `Unit3` | tangent basis from the axis of the smallest component (and an exponential-map retraction) | `s2_gtsam_basis`, `s2_tangent_to_gtsam`, `s2_tangent_from_gtsam`, `s2_jacobian_to_gtsam` |
| GTSAM `localCoordinates` | `X.localCoordinates(Y)` is $Y \ominus X$ | `gtsam_local_coordinates` |
| GTSAM `PreintegratedImuMeasurements`, `ImuFactor` (`lieax.imu`) | none in the preintegrated vector, `preintMeasCov`, the bias Jacobians and the factor's residual: all $(\theta, \Delta p, \Delta v)$, biases $(b_a, b_g)$ as `ConstantBias.vector()`; the residual is by default `ImuFactorErrorMode.Logmap`'s (GTSAM 4.3's default for fresh parameters), $\mathrm{Log}_{SE_2(3)}(x_j^{-1}\hat x_j)$ rotation first, and with `error_mode="component_wise"` `ComponentWise`'s, $(\mathrm{Log}(R_j^\top\hat R_j), R_j^\top(\hat p_j - p_j), R_j^\top(\hat v_j - v_j))$ (Logmap's position and velocity rows are ComponentWise's times $J_l^{-1}(r_\theta)$; both are whitened by `residualCovariance()`); the pose Jacobians' columns are Pose3's $(\omega, v)$ | `se3_jacobian_from_gtsam(H, rows=False)` for `H1`, `H3`; `H2`, `H4`, `H5` as they are |
| GTSAM `PreintegrationParams.omegaCoriolis`, `PreintegratedCombinedMeasurements` (`lieax.imu`) | none: `ImuParams.omega_coriolis` is `omegaCoriolis` (4.3's exact rotating-frame `predictPIM`; its `use2ndOrderCoriolis` is ignored there as here); `preintegrate_combined`'s 15×15 covariance is `preintMeasCov()` in $(\theta, \Delta p, \Delta v, b_a, b_g)$, `BiasRandomWalk` is `biasAccCovariance`, `biasOmegaCovariance` | none needed |
| GTSAM `CombinedImuFactor` (`lieax.imu.combined_imu_factor`) | rows 1–9 are `ImuFactor`'s; rows 10–15 are $b_j - b_i$ (as `bias_random_walk_factor`), GTSAM's $b_i - b_j$: negated in the error and in `H1`…`H6`, and its noise model's covariance (`residualCovariance()`) is $D \Sigma_r D$, $D = \mathrm{diag}(I_9, -I_6)$; the whitened cost is the same | negate rows 10–15, then `se3_jacobian_from_gtsam(H, rows=False)` for `H1`, `H3` |
| left perturbation (e.g. Barfoot, Ceres' quaternions) | $\mathrm{Exp}(\xi_L) X = X \mathrm{Exp}(\xi_R)$, so $\xi_L = \mathrm{Ad}_X \xi_R$ | `left_from_right_tangent`, `right_from_left_tangent`, `left_from_right_jacobian`, `right_from_left_jacobian` |
| Ceres `QuaternionManifold` | $x \boxplus \delta = [\cos|\delta|, \tfrac{\sin|\delta|}{|\delta|}\delta] \otimes x$: left, half angle ($\omega_L = 2\delta$), wxyz; `EigenQuaternionManifold` the same in xyzw | `ceres_quaternion_plus`, `ceres_quaternion_minus`, `ceres_quaternion_plus_jacobian`, `tangent_from_ceres_delta`, `tangent_to_ceres_delta`, `jacobian_from_ceres_delta`, `jacobian_to_ceres_delta` |
| SciPy, ROS, Eigen `coeffs()` | quaternion xyzw; ROS/TUM poses `(x, y, z, qx, qy, qz, qw)` | `wxyz_to_xyzw`, `xyzw_to_wxyz`, `se3_from_xyz_xyzw`, `se3_to_xyz_xyzw` |

Jacobians follow lieax's layout: `J` of shape `(out_dim, in_dim)` (or batched `(*batch, out, in)`),
with $f(X \oplus \delta) \ominus f(X) \approx J \delta$.
"""

import jax
import jax.numpy as jnp
import numpy as np
from jax.typing import ArrayLike

from ._checks import as_float_array, check_last_axis
from ._linalg import cross, dot, matvec, quat_conjugate, quat_multiply, rotate_back
from .groups import S2, SE3, SO3, AbstractGroup, AbstractManifold, Sim3, kernels

__all__ = [
    "ceres_quaternion_minus",
    "ceres_quaternion_plus",
    "ceres_quaternion_plus_jacobian",
    "gtsam_local_coordinates",
    "jacobian_from_ceres_delta",
    "jacobian_to_ceres_delta",
    "left_from_right_jacobian",
    "left_from_right_tangent",
    "right_from_left_jacobian",
    "right_from_left_tangent",
    "s2_gtsam_basis",
    "s2_jacobian_to_gtsam",
    "s2_tangent_from_gtsam",
    "s2_tangent_to_gtsam",
    "se23_jacobian_from_gtsam",
    "se23_jacobian_to_gtsam",
    "se23_tangent_from_gtsam",
    "se23_tangent_to_gtsam",
    "se3_from_xyz_xyzw",
    "se3_jacobian_from_gtsam",
    "se3_jacobian_to_gtsam",
    "se3_tangent_from_gtsam",
    "se3_tangent_to_gtsam",
    "se3_to_xyz_xyzw",
    "sim3_from_gtsam",
    "sim3_jacobian_from_gtsam",
    "sim3_jacobian_to_gtsam",
    "sim3_tangent_from_gtsam",
    "sim3_tangent_to_gtsam",
    "sim3_to_gtsam",
    "tangent_from_ceres_delta",
    "tangent_to_ceres_delta",
    "wxyz_to_xyzw",
    "xyzw_to_wxyz",
]

# ---- GTSAM: rotation-first tangents ---------------------------------------------------------------

_SE3_TO_GTSAM = np.array([3, 4, 5, 0, 1, 2])  # gtsam (ω, v)[i] = lieax (v, ω)[_SE3_TO_GTSAM[i]]
_SIM3_TO_GTSAM = np.array([3, 4, 5, 0, 1, 2, 6])  # gtsam (ω, v, λ) from lieax (v, ω, σ)
_SE23_TO_GTSAM = np.array([3, 4, 5, 0, 1, 2, 6, 7, 8])  # gtsam (ω, p, v) from lieax (p, ω, v)
_SE3_FROM_GTSAM = np.argsort(_SE3_TO_GTSAM)
_SIM3_FROM_GTSAM = np.argsort(_SIM3_TO_GTSAM)


def _permute_jacobian(jacobian, order, rows, cols, size):
    jacobian = as_float_array(jacobian, "jacobian")
    if rows:
        if jacobian.shape[-2] != size:
            raise ValueError(
                f"jacobian rows must be {size} (a tangent), got shape {jacobian.shape}."
            )
        jacobian = jacobian[..., order, :]
    if cols:
        if jacobian.shape[-1] != size:
            raise ValueError(
                f"jacobian columns must be {size} (a tangent), got shape {jacobian.shape}."
            )
        jacobian = jacobian[..., :, order]
    return jacobian


def se3_tangent_to_gtsam(xi: ArrayLike) -> jax.Array:
    r"""lieax SE3 tangent $(v, \omega)$ to GTSAM's `Pose3` tangent $(\omega, v)$; shape `(*batch, 6)`."""
    return check_last_axis(xi, 6, "SE3 tangent")[..., _SE3_TO_GTSAM]


def se3_tangent_from_gtsam(xi_gtsam: ArrayLike) -> jax.Array:
    r"""GTSAM `Pose3` tangent $(\omega, v)$ to lieax's $(v, \omega)$."""
    return check_last_axis(xi_gtsam, 6, "GTSAM Pose3 tangent")[..., _SE3_FROM_GTSAM]


def se3_jacobian_to_gtsam(
    jacobian: ArrayLike, *, rows: bool = True, cols: bool = True
) -> jax.Array:
    r"""A lieax Jacobian to GTSAM's `H`: rows permuted when the output is an SE3 tangent, columns
    when the input is ($H = P J P^\top$, $P$ the block swap). Set `rows=False` for vector outputs
    (e.g. `transformFrom`'s `Hself` is `J` with permuted columns only)."""
    return _permute_jacobian(jacobian, _SE3_TO_GTSAM, rows, cols, 6)


def se3_jacobian_from_gtsam(
    jacobian: ArrayLike, *, rows: bool = True, cols: bool = True
) -> jax.Array:
    """GTSAM's `H` to a lieax Jacobian (inverse of `se3_jacobian_to_gtsam`)."""
    return _permute_jacobian(jacobian, _SE3_FROM_GTSAM, rows, cols, 6)


def sim3_tangent_to_gtsam(xi: ArrayLike) -> jax.Array:
    r"""lieax Sim3 tangent $(v, \omega, \sigma)$ to GTSAM's `Similarity3` tangent $(\omega, v, \lambda)$
    ($\lambda = \sigma$: GTSAM's algebra element $[[\omega]_\times, v; 0, -\lambda]$ is lieax's
    $[[\omega]_\times + \sigma I, v; 0, 0]$ minus $\sigma I_4$, the same projective transform)."""
    return check_last_axis(xi, 7, "Sim3 tangent")[..., _SIM3_TO_GTSAM]


def sim3_tangent_from_gtsam(xi_gtsam: ArrayLike) -> jax.Array:
    r"""GTSAM `Similarity3` tangent $(\omega, v, \lambda)$ to lieax's $(v, \omega, \sigma)$."""
    return check_last_axis(xi_gtsam, 7, "GTSAM Similarity3 tangent")[..., _SIM3_FROM_GTSAM]


def sim3_jacobian_to_gtsam(
    jacobian: ArrayLike, *, rows: bool = True, cols: bool = True
) -> jax.Array:
    """A lieax Jacobian with Sim3 tangents to GTSAM's ordering (see `se3_jacobian_to_gtsam`)."""
    return _permute_jacobian(jacobian, _SIM3_TO_GTSAM, rows, cols, 7)


def sim3_jacobian_from_gtsam(
    jacobian: ArrayLike, *, rows: bool = True, cols: bool = True
) -> jax.Array:
    """GTSAM's `Similarity3` Jacobian ordering to lieax's."""
    return _permute_jacobian(jacobian, _SIM3_FROM_GTSAM, rows, cols, 7)


def se23_tangent_to_gtsam(xi: ArrayLike) -> jax.Array:
    r"""lieax SE23 tangent $(\rho_p, \omega, \rho_v)$ to GTSAM's `NavState` tangent
    $(\delta R, \delta p, \delta v)$; shape `(*batch, 9)`."""
    return check_last_axis(xi, 9, "SE23 tangent")[..., _SE23_TO_GTSAM]


def se23_tangent_from_gtsam(xi_gtsam: ArrayLike) -> jax.Array:
    r"""GTSAM `NavState` tangent $(\delta R, \delta p, \delta v)$ to lieax's $(\rho_p, \omega, \rho_v)$
    (the permutation is its own inverse)."""
    return check_last_axis(xi_gtsam, 9, "GTSAM NavState tangent")[..., _SE23_TO_GTSAM]


def se23_jacobian_to_gtsam(
    jacobian: ArrayLike, *, rows: bool = True, cols: bool = True
) -> jax.Array:
    """A lieax Jacobian with SE23 tangents to GTSAM's `NavState` ordering (see
    `se3_jacobian_to_gtsam`)."""
    return _permute_jacobian(jacobian, _SE23_TO_GTSAM, rows, cols, 9)


def se23_jacobian_from_gtsam(
    jacobian: ArrayLike, *, rows: bool = True, cols: bool = True
) -> jax.Array:
    """GTSAM's `NavState` Jacobian ordering to lieax's."""
    return _permute_jacobian(jacobian, _SE23_TO_GTSAM, rows, cols, 9)


def sim3_to_gtsam(transform: Sim3) -> tuple[jax.Array, jax.Array, jax.Array]:
    r"""`(R, t_gtsam, s)` for `gtsam.Similarity3(R, t_gtsam, s)`: GTSAM stores
    $[R, t_g; 0, 1/s]$ and maps $p \mapsto s(Rp + t_g)$, so $t_g = t / s$."""
    if not isinstance(transform, Sim3):
        raise TypeError(f"sim3_to_gtsam needs a Sim3, got {type(transform).__name__}.")
    scale = transform.scale()
    return transform.rotation().as_matrix(), transform.translation() / scale[..., None], scale


def sim3_from_gtsam(
    rotation_matrix: ArrayLike, translation_gtsam: ArrayLike, scale: ArrayLike
) -> Sim3:
    r"""The Sim3 of GTSAM's `Similarity3(R, t_gtsam, s)` (`.rotation().matrix()`, `.translation()`,
    `.scale()`): $t = s\,t_g$."""
    scale = as_float_array(scale, "scale")
    rotation = SO3.from_matrix(rotation_matrix)
    translation = scale[..., None] * check_last_axis(translation_gtsam, 3, "GTSAM translation")
    return Sim3.from_rotation_translation_scale(rotation, translation, scale)


def gtsam_local_coordinates(x: AbstractManifold, y: AbstractManifold) -> jax.Array:
    r"""GTSAM's `x.localCoordinates(y)`, that is $y \ominus x$ = `y.rminus(x)` in lieax's order (in
    lieax's tangent ordering; convert with the `*_tangent_to_gtsam` functions)."""
    return y.rminus(x)


# ---- GTSAM: Unit3's tangent basis -----------------------------------------------------------------


def s2_gtsam_basis(p: ArrayLike) -> jax.Array:
    r"""GTSAM's `Unit3::basis()`: $b_1 = p \times a / |p \times a|$, $b_2 = p \times b_1 / |p \times b_1|$,
    with $a$ the axis of the smallest $|p_i|$ (x on ties, then y); shape `(*batch, 3, 2)`.
    Deterministic, smooth inside each region, discontinuous where the smallest component changes."""
    p = check_last_axis(p, 3, "S2 direction")
    magnitude = jnp.abs(p)
    mx, my, mz = magnitude[..., 0], magnitude[..., 1], magnitude[..., 2]
    pick_x = (mx <= my) & (mx <= mz)
    pick_y = ~pick_x & (my <= mx) & (my <= mz)
    eye = jnp.eye(3, dtype=p.dtype)
    axis = jnp.where(pick_x[..., None], eye[0], jnp.where(pick_y[..., None], eye[1], eye[2]))
    b1 = cross(p, axis)
    b1 = b1 / jnp.sqrt(dot(b1, b1))[..., None]
    b2 = cross(p, b1)
    b2 = b2 / jnp.sqrt(dot(b2, b2))[..., None]
    return jnp.stack([b1, b2], axis=-1)


def _s2_rotation(p):
    r"""$C_p = B_{p,\mathrm{lieax}}^\top B_{p,\mathrm{gtsam}}$ (2×2, orthogonal): $\xi_{lieax} = C_p \xi_{gtsam}$."""
    return jnp.swapaxes(kernels.s2_basis(p), -1, -2) @ s2_gtsam_basis(p)


def s2_tangent_to_gtsam(direction: S2 | ArrayLike, xi: ArrayLike) -> jax.Array:
    r"""lieax S2 tangent coordinates at `direction` (an `S2` or unit vectors) to GTSAM `Unit3`'s:
    $\xi_g = C_p^\top \xi$ (both bases span the tangent plane, so they differ by a 2×2 rotation
    or reflection $C_p$)."""
    p = direction.parameters() if isinstance(direction, S2) else direction
    return matvec(jnp.swapaxes(_s2_rotation(p), -1, -2), check_last_axis(xi, 2, "S2 tangent"))


def s2_tangent_from_gtsam(direction: S2 | ArrayLike, xi_gtsam: ArrayLike) -> jax.Array:
    r"""GTSAM `Unit3` tangent coordinates at `direction` to lieax's: $\xi = C_p \xi_g$."""
    p = direction.parameters() if isinstance(direction, S2) else direction
    return matvec(_s2_rotation(p), check_last_axis(xi_gtsam, 2, "Unit3 tangent"))


def s2_jacobian_to_gtsam(
    jacobian: ArrayLike, *, row_direction: S2 | None = None, col_direction: S2 | None = None
) -> jax.Array:
    r"""A lieax Jacobian with S2 output tangent at `row_direction` and/or S2 input tangent at
    `col_direction` (each an `S2` or `None` when that side is not an S2) to GTSAM's `Unit3`
    bases: $H = C_{out}^\top J C_{in}$. Valid at the linearization point, where GTSAM's
    exponential retraction and lieax's normalizing one agree to first order."""
    jacobian = as_float_array(jacobian, "jacobian")
    if row_direction is not None:
        jacobian = jnp.swapaxes(_s2_rotation(row_direction.parameters()), -1, -2) @ jacobian
    if col_direction is not None:
        jacobian = jacobian @ _s2_rotation(col_direction.parameters())
    return jacobian


# ---- left and right perturbations ----------------------------------------------------------------


def left_from_right_tangent(element: AbstractGroup, xi_right: ArrayLike) -> jax.Array:
    r"""$\xi_L = \mathrm{Ad}_X \xi_R$, so that $\mathrm{Exp}(\xi_L)\,X = X\,\mathrm{Exp}(\xi_R)$."""
    return matvec(element.adjoint(), xi_right)


def right_from_left_tangent(element: AbstractGroup, xi_left: ArrayLike) -> jax.Array:
    r"""$\xi_R = \mathrm{Ad}_X^{-1} \xi_L = \mathrm{Ad}_{X^{-1}} \xi_L$."""
    return matvec(element.inverse().adjoint(), xi_left)


def left_from_right_jacobian(
    jacobian: ArrayLike, *, at: AbstractGroup | None = None, value: AbstractGroup | None = None
) -> jax.Array:
    r"""The Jacobian for left perturbations, $f(\mathrm{Exp}(\delta) X) \approx \mathrm{Exp}(J_L\delta) f(X)$,
    from lieax's right one: $J_L = \mathrm{Ad}_{f(X)}\,J_R\,\mathrm{Ad}_X^{-1}$. `at` is $X$ (a group
    element, or `None` for a vector input) and `value` is $f(X)$ (`None` for a vector output)."""
    jacobian = as_float_array(jacobian, "jacobian")
    if value is not None:
        jacobian = value.adjoint() @ jacobian
    if at is not None:
        jacobian = jacobian @ at.inverse().adjoint()
    return jacobian


def right_from_left_jacobian(
    jacobian: ArrayLike, *, at: AbstractGroup | None = None, value: AbstractGroup | None = None
) -> jax.Array:
    r"""lieax's (right) Jacobian from a left one: $J_R = \mathrm{Ad}_{f(X)}^{-1}\,J_L\,\mathrm{Ad}_X$."""
    jacobian = as_float_array(jacobian, "jacobian")
    if value is not None:
        jacobian = value.inverse().adjoint() @ jacobian
    if at is not None:
        jacobian = jacobian @ at.adjoint()
    return jacobian


# ---- Ceres: half-angle, left-multiplied quaternion plus -----------------------------------------


def ceres_quaternion_plus(q: ArrayLike, delta: ArrayLike) -> jax.Array:
    r"""Ceres' `QuaternionManifold::Plus` on wxyz arrays: $[\cos|\delta|, \tfrac{\sin|\delta|}{|\delta|}\delta]
    \otimes q$ (rotation vector $2\delta$ applied on the left; $q$ itself at $\delta = 0$)."""
    q = check_last_axis(q, 4, "quaternion", "wxyz")
    delta = check_last_axis(delta, 3, "Ceres quaternion delta")
    # (cos|δ|, sin|δ|/|δ| δ), NaN-free at 0; to_parameters: raw derivatives, not SO3's carrier
    q_delta = kernels.so3_to_parameters(kernels.so3_exp(2.0 * delta))
    return quat_multiply(q_delta, q)


def ceres_quaternion_minus(y: ArrayLike, x: ArrayLike) -> jax.Array:
    r"""Ceres' `QuaternionManifold::Minus` on wxyz arrays: with $(w, u) = y \otimes \bar x$,
    $\mathrm{atan2}(|u|, w)\,u / |u|$ (0 where $u = 0$); `ceres_quaternion_plus(x, minus(y, x)) == y`."""
    y = check_last_axis(y, 4, "quaternion y", "wxyz")
    x = check_last_axis(x, 4, "quaternion x", "wxyz")
    ambient = quat_multiply(y, quat_conjugate(x))
    w, u = ambient[..., :1], ambient[..., 1:]
    squared = dot(u, u)[..., None]
    positive = squared > 0.0
    norm = jnp.sqrt(jnp.where(positive, squared, 1.0))
    return jnp.where(positive, jnp.arctan2(norm, w) / norm, 0.0) * u


def ceres_quaternion_plus_jacobian(q: ArrayLike) -> jax.Array:
    r"""Ceres' `PlusJacobian`: $\partial (x \boxplus \delta) / \partial \delta$ at 0, shape `(*batch, 4, 3)`
    (wxyz rows): column $i$ is $(0, e_i) \otimes q$."""
    q = check_last_axis(q, 4, "quaternion", "wxyz")
    eye = jnp.eye(3, dtype=q.dtype)
    pure = jnp.concatenate([jnp.zeros((3, 1), dtype=q.dtype), eye], axis=-1)  # (0, e_i)
    columns = quat_multiply(pure, q[..., None, :])  # (*batch, 3, 4)
    return jnp.swapaxes(columns, -1, -2)


def tangent_from_ceres_delta(rotation: SO3, delta: ArrayLike) -> jax.Array:
    r"""The lieax (right) tangent of a Ceres quaternion increment at $R$:
    $x \boxplus \delta = \mathrm{Exp}(2\delta) R = R\,\mathrm{Exp}(2 R^\top \delta)$, so $\omega = 2R^\top\delta$."""
    return 2.0 * rotate_back(rotation.as_matrix(), check_last_axis(delta, 3, "Ceres delta"))


def tangent_to_ceres_delta(rotation: SO3, omega: ArrayLike) -> jax.Array:
    r"""The Ceres increment of a lieax tangent at $R$: $\delta = \tfrac12 R\omega$."""
    return 0.5 * matvec(rotation.as_matrix(), check_last_axis(omega, 3, "SO3 tangent"))


def jacobian_to_ceres_delta(jacobian: ArrayLike, rotation: SO3) -> jax.Array:
    r"""A lieax Jacobian with respect to an SO3 input (columns: right tangent) to the Jacobian with
    respect to Ceres' $\delta$ at that rotation: $J_\delta = J \cdot 2R^\top$ (Ceres multiplies the
    ambient Jacobian by `PlusJacobian`, which is this for the quaternion)."""
    return as_float_array(jacobian, "jacobian") @ (2.0 * jnp.swapaxes(rotation.as_matrix(), -1, -2))


def jacobian_from_ceres_delta(jacobian: ArrayLike, rotation: SO3) -> jax.Array:
    r"""Jacobian columns with respect to Ceres' $\delta$ to lieax's right tangent: $J = J_\delta \cdot \tfrac12 R$."""
    return as_float_array(jacobian, "jacobian") @ (0.5 * rotation.as_matrix())


# ---- storage orders ------------------------------------------------------------------------------


def wxyz_to_xyzw(q: ArrayLike) -> jax.Array:
    """Scalar-first quaternions (lieax, GTSAM's `Quaternion(w, x, y, z)`, Ceres) to scalar-last
    (SciPy, ROS, Eigen's `coeffs()`, Ceres' `EigenQuaternionManifold`)."""
    return jnp.roll(check_last_axis(q, 4, "quaternion", "wxyz"), -1, axis=-1)


def xyzw_to_wxyz(q: ArrayLike) -> jax.Array:
    """Scalar-last quaternions to scalar-first."""
    return jnp.roll(check_last_axis(q, 4, "quaternion", "xyzw"), 1, axis=-1)


def se3_from_xyz_xyzw(pose: ArrayLike) -> SE3:
    """An SE3 from ROS `Pose` / TUM trajectory order `(x, y, z, qx, qy, qz, qw)`, shape `(*batch, 7)`
    (the quaternion is used as given; call `.normalize()` on data that may not be unit)."""
    pose = check_last_axis(pose, 7, "pose", "x, y, z, qx, qy, qz, qw")
    return SE3(jnp.concatenate([xyzw_to_wxyz(pose[..., 3:]), pose[..., :3]], axis=-1))


def se3_to_xyz_xyzw(transform: SE3) -> jax.Array:
    """`(x, y, z, qx, qy, qz, qw)` of an SE3 (ROS `Pose`, TUM trajectories)."""
    params = transform.parameters()
    return jnp.concatenate([params[..., 4:], wxyz_to_xyzw(params[..., :4])], axis=-1)
