r"""Bearing-range factors: landmarks seen from poses (GTSAM's `BearingRangeFactor2D` and
`BearingRangeFactor3D`), one `lieax.factorgraph.Factor` kind per call of `bearing_range_factor`.

2D: a pose $X \in SE(2)$, a landmark $l \in \mathbb{R}^2$, a measured bearing $Z \in SO(2)$ and
range $\rho$; with $d = X^{-1} l$,
$$e = \big(\mathrm{Log}(Z^{-1} \hat Z),\ |d| - \rho\big), \qquad \hat Z = X.\mathrm{bearing}(l),$$
the bearing residual wrapped into $(-\pi, \pi]$ (`SO2.rminus`). It is GTSAM's error,
`measured.localCoordinates(predicted)` (ExpressionFactor.h's $-\mathrm{Local}(\hat z, z)$,
BearingRange.h stacking Rot2's and the range's). Closed-form blocks (`bearing_range_jacobians_2d`;
SO2's Log has derivative 1, so they are those of `SE2.bearing` and `SE2.range`), with
$q = |d|^2$, $r = |d|$:
$$\frac{\partial e_\theta}{\partial X} = \frac{(d_y,\ -d_x,\ -q)}{q}, \quad
\frac{\partial e_\theta}{\partial l} = \frac{(J d)^\top R^\top}{q}, \quad
\frac{\partial e_r}{\partial X} = \Big(-\frac{d^\top}{r},\ 0\Big), \quad
\frac{\partial e_r}{\partial l} = \frac{d^\top R^\top}{r},$$
zero where $d = 0$ (the landmark at the pose: the documented values of `SE2.bearing` / `range`).

3D: $X \in SE(3)$, $l \in \mathbb{R}^3$, a measured direction $m \in S^2$ (in the pose's frame)
and range $\rho$; with $b = X.\mathrm{bearing}(l)$ and $\theta$ the angle between $m$ and $b$,
$$e = \Big(\frac{\theta}{\sin\theta}\,B_m^\top b,\ |d| - \rho\Big),$$
the first part the sphere's logarithm of $b$ at $m$ in lieax's basis $B_m$ (`S2.basis`), of norm
$\theta$ (`direction_error`). GTSAM's is $-$`b.localCoordinates(m)`, the logarithm of $m$ at $b$
in its basis at $b$ (Unit3.cpp), also of norm $\theta$: the costs agree when the two bearing
coordinates have equal noise (GTSAM's `Sigmas((σ, σ, σ_r))`); GTSAM's Jacobian keeps only the
prediction's (its `Local`'s derivative is taken as the identity), lieax's is the residual's own,
through the rules of `SE3.bearing` / `range` (`lieax.value_and_jacobian`).
"""

import math
from collections.abc import Sequence

import jax
import jax.numpy as jnp
import numpy as np
from jax.typing import ArrayLike

from .._linalg import dot, horner
from ..factorgraph import Factor, VarRef
from ..groups import S2, SE2, SE3, SO2, kernels
from ..lstsq import AbstractLoss

# θ/sin θ = asin(s)/s = Σ (2k)! / (4^k (k!)² (2k + 1)) s^(2k) for cos θ > 0, summed in s² below
# _SERIES_LIMIT (the next term, 0.0115 s^16, is below 1.2e-18 there); above, atan2(s, c) / s, whose
# derivative loses about eps / s² (1e-14 in float64, 1e-5 relative in float32) at the switch
_SERIES_LIMIT = 1e-2
_THETA_OVER_SINE = tuple(
    math.factorial(2 * k) / (4**k * math.factorial(k) ** 2 * (2 * k + 1)) for k in range(8)
)


def direction_error(measured: ArrayLike, predicted: ArrayLike) -> jax.Array:
    r"""$(\theta / \sin\theta)\,B_m^\top b$ for unit vectors $m$ = `measured`, $b$ = `predicted`
    (`(*batch, 3)`): the sphere's logarithm of $b$ at $m$ in `S2.basis(m)`, of norm $\theta$, the
    angle between them (module docstring); it depends on the direction of $b$ only (the derivative
    along $b$ is 0). $\theta / \sin\theta$ is summed as a series in
    $\sin^2\theta = |B_m^\top b|^2 / |b|^2$ near $b = m$ (no square root of it, so derivatives of
    any order are finite there), $\mathrm{atan2}(|B_m^\top b|, m^\top b) / |B_m^\top b|$ above
    $\sin^2\theta = 10^{-2}$. At $b = -m$ (to rounding: $\sin\theta \le \epsilon$), where the
    logarithm has no direction, it is $(\pi, 0)$ (GTSAM's `Unit3::localCoordinates` returns the
    same there) with derivative 0; near it the derivative grows like $1 / \sin\theta$."""
    projected = kernels.s2_error(measured, predicted)  # B_m^T b
    sine_squared = dot(projected, projected)[..., None]  # |b|² sin² θ
    cosine = dot(measured, predicted)[..., None]  # |b| cos θ
    series = (sine_squared < _SERIES_LIMIT * (sine_squared + cosine**2)) & (cosine > 0)
    eps = jnp.finfo(projected.dtype).eps
    antipode = (cosine < 0) & (sine_squared <= (eps * cosine) ** 2)  # θ within rounding of π
    sine = jnp.sqrt(jnp.where(series | antipode, 1.0, sine_squared))
    closed = jnp.arctan2(sine, cosine) / sine
    # the series in sin² θ, over |b| = sqrt(|b|² sin² θ + |b|² cos² θ): a function of b's direction
    length_squared = jnp.where(series, sine_squared + cosine**2, 1.0)
    s = jnp.where(series, sine_squared / length_squared, 0.0)
    summed = horner(_THETA_OVER_SINE, s)
    error = jnp.where(series, summed / jnp.sqrt(length_squared), closed) * projected
    pi_along_first = jnp.zeros_like(projected).at[..., 0].set(jnp.pi)
    return jnp.where(antipode, pi_along_first, error)


def bearing_range_error(
    pose: SE2 | SE3, landmark: ArrayLike, measured: tuple[SO2 | S2, ArrayLike]
) -> jax.Array:
    r"""The unwhitened residual of one bearing-range measurement (module docstring): `pose` an
    `SE2` (or `SE3`), `landmark` `(2,)` (or `(3,)`), `measured` a pair `(bearing, range)` with
    the bearing an `SO2` (or `S2`); shape `(2,)` (or `(3,)`). Batched arguments broadcast."""
    bearing, range_ = measured
    predicted = pose.bearing(landmark)
    if isinstance(pose, SE2):
        bearing_error = predicted.rminus(bearing)
    else:
        bearing_error = direction_error(bearing.parameters(), predicted.parameters())
    return jnp.concatenate([bearing_error, (pose.range(landmark) - range_)[..., None]], axis=-1)


def bearing_range_jacobians_2d(
    pose: SE2, landmark: ArrayLike, measured: tuple[SO2, ArrayLike]
) -> tuple[jax.Array, tuple[jax.Array, jax.Array]]:
    r"""`(e, (J_e_pose, J_e_landmark))` for an `SE2` pose: the residual of `bearing_range_error`
    and its closed-form blocks `(2, 3)` and `(2, 2)` (module docstring)."""
    error = bearing_range_error(pose, landmark, measured)
    params = pose.parameters()
    local = kernels.se2_transform_to(params, landmark)  # d
    u, length, nonzero = kernels.unit_and_length(local)  # d / r, r (1 and the x axis at d = 0)
    nonzero = nonzero[0]
    bearing_row = jnp.where(nonzero, kernels.so2_perp(u) / length, 0.0)  # (J d)^T / q
    range_row = jnp.where(nonzero, u, 0.0)  # d^T / r
    J_e_pose = jnp.stack(
        [
            jnp.concatenate([-bearing_row, -jnp.where(nonzero, 1.0, 0.0)[None]]),
            jnp.concatenate([-range_row, jnp.zeros(1, local.dtype)]),
        ]
    )
    # row^T R^T = (R row)^T: the landmark blocks are the rows rotated into the world frame
    J_e_landmark = jnp.stack(
        [kernels.so2_rotate(params[:2], bearing_row), kernels.so2_rotate(params[:2], range_row)]
    )
    return error, (J_e_pose, J_e_landmark)


def bearing_range_factor(
    pose: VarRef,
    landmark: VarRef,
    bearings: SO2 | S2 | ArrayLike,
    ranges: ArrayLike,
    *,
    sigmas: ArrayLike | Sequence[float] | None = None,
    sqrt_information: ArrayLike | None = None,
    information: ArrayLike | None = None,
    covariance: ArrayLike | None = None,
    loss: AbstractLoss | None = None,
    closed_form: bool = True,
    name: str = "bearing_range",
) -> Factor:
    r"""A `Factor` kind of bearing-range measurements of landmarks from poses, 2D or 3D (GTSAM's
    `BearingRangeFactor2D` / `BearingRangeFactor3D`; residuals and blocks in the module
    docstring):

    ```python
    sightings = bearing_range_factor(poses[i], landmarks[j], bearings, ranges, sigmas=(0.05, 0.1))
    ```

    **Arguments:**

    - `pose`, `landmark`: `var[index]` references, index arrays `(m,)`: an `SE2` `Var` with
      landmarks `(n, 2)`, or an `SE3` `Var` with landmarks `(n, 3)`.
    - `bearings`: the measured bearings in the pose's frame, `(m,)`: an `SO2` or angles in
      radians (2D); an `S2` or vectors `(m, 3)`, normalized (3D).
    - `ranges`: the measured distances `(m,)`.
    - `sigmas`: standard deviations of the residual's entries, `(bearing, range)` in 2D,
      `(bearing, bearing, range)` in 3D (or `(m, k)`): GTSAM's `noiseModel::Diagonal::Sigmas`.
      Or one of `sqrt_information`, `information`, `covariance` (as `Factor`'s); default
      identity.
    - `loss`: a robust loss (`lieax.lstsq.Huber`, ...) or `None`.
    - `closed_form`: 2D only: the closed-form blocks `bearing_range_jacobians_2d` (default);
      `False` differentiates the residual through the groups' rules, as 3D always does.
    - `name`: the factor kind's name in messages.

    **Returns:** a `Factor` over `(pose, landmark)` with data `(bearings, ranges)`.
    Raises `TypeError` / `ValueError` naming the factor kind when the variables, measurements
    or sigmas do not fit.
    """
    what = f"bearing_range_factor {name!r}"
    if not isinstance(pose, VarRef) or not isinstance(landmark, VarRef):
        raise TypeError(f"{what}: pose and landmark must be var[index] references.")
    group = type(pose.var.value)
    if group not in (SE2, SE3):
        raise TypeError(f"{what}: the pose Var must hold SE2 or SE3 poses, got {group.__name__}.")
    dim = group.space_dim
    dtype = pose.var.value.dtype
    points = landmark.var.value
    if not hasattr(points, "shape") or points.ndim != 2 or points.shape[1] != dim:
        shape = getattr(points, "shape", type(points).__name__)
        raise ValueError(f"{what}: {group.__name__} poses need landmarks of shape (n, {dim}), "
                         f"got {shape}.")  # fmt: skip
    if points.dtype != dtype:
        raise TypeError(f"{what}: the landmarks have dtype {points.dtype}, the poses {dtype}.")
    count = len(np.atleast_1d(np.asarray(pose.index)))
    measured = (_bearings(bearings, group, dtype, count, what), _ranges(ranges, dtype, count, what))
    if sigmas is not None:
        if sqrt_information is not None or information is not None or covariance is not None:
            raise ValueError(f"{what}: give sigmas or one of sqrt_information, information and "
                             "covariance, not both.")  # fmt: skip
        sqrt_information = _sqrt_information_of_sigmas(sigmas, dim, what)
    blocks = bearing_range_jacobians_2d if closed_form and group is SE2 else None
    return Factor(
        bearing_range_error,
        (pose, landmark),
        measured,
        sqrt_information=sqrt_information,
        information=information,
        covariance=covariance,
        loss=loss,
        jacobian_fn=blocks,
        name=name,
    )


def _bearings(bearings, group, dtype, count, what):
    """The measured bearings as a batched `SO2` (2D) or `S2` (3D) of `count` instances."""
    expected = SO2 if group is SE2 else S2
    if isinstance(bearings, (SO2, S2)) and not isinstance(bearings, expected):
        raise TypeError(f"{what}: {group.__name__} poses need {expected.__name__} bearings, "
                        f"got {type(bearings).__name__}.")  # fmt: skip
    if not isinstance(bearings, expected):
        array = np.asarray(bearings, dtype=dtype)
        shape = (count,) if group is SE2 else (count, 3)
        if array.shape != shape:
            layout = "angles" if group is SE2 else "direction vectors"
            raise ValueError(f"{what}: bearings must be {expected.__name__} or {layout} of shape "
                             f"{shape}, got shape {array.shape}.")  # fmt: skip
        rows = array.reshape(count, -1)
        bad = ~np.all(np.isfinite(rows), axis=1) | ((group is SE3) & ~np.any(rows, axis=1))
        if np.any(bad):
            raise ValueError(
                f"{what}: bearing {np.flatnonzero(bad)[0]} is not finite (or a zero vector)."
            )
        array = jnp.asarray(array)
        return SO2.from_angle(array) if group is SE2 else S2.from_vector(array)
    if bearings.batch_shape != (count,):
        raise ValueError(f"{what}: bearings must have batch shape ({count},), got "
                         f"{bearings.batch_shape}.")  # fmt: skip
    if bearings.dtype != dtype:
        raise TypeError(f"{what}: bearings have dtype {bearings.dtype}, the poses {dtype}.")
    return bearings


def _ranges(ranges, dtype, count, what):
    array = np.asarray(ranges, dtype=dtype)
    if array.shape != (count,):
        raise ValueError(f"{what}: ranges must have shape ({count},), got {array.shape}.")
    if not np.all(np.isfinite(array)):
        raise ValueError(f"{what}: range {np.flatnonzero(~np.isfinite(array))[0]} is not finite.")
    return jnp.asarray(array)


def _sqrt_information_of_sigmas(sigmas, dim, what):
    r"""$\mathrm{diag}(1/\sigma)$, `(k, k)` or `(m, k, k)`, $k$ = 2 (2D) or 3 (3D)."""
    sigmas = np.asarray(sigmas, dtype=np.float64)
    if sigmas.ndim not in (1, 2) or sigmas.shape[-1] != dim:
        raise ValueError(f"{what}: sigmas must have shape ({dim},) or (m, {dim}), got "
                         f"{sigmas.shape}.")  # fmt: skip
    if not np.all(np.isfinite(sigmas) & (sigmas > 0)):
        raise ValueError(f"{what}: sigmas must be positive and finite, got {sigmas}.")
    return (1.0 / sigmas)[..., :, None] * np.eye(dim)
