r"""Camera factors for `lieax.factorgraph`, and the behind-the-camera (cheirality) policy.

`projection_factor` (SE3 pose × world point → pixel, `Cal3_S2` or `Cal3DS2`), `stereo_factor`
(→ $(u_L, u_R, v)$, `Cal3_S2Stereo`) and `bearing_factor` (→ S2's tangent) each return one
`lieax.factorgraph.Factor` with closed-form Jacobian blocks (`jacobian_fn`); the pose variable
holds $T_{wc}$ (camera to world, as GTSAM's `GenericProjectionFactor`, `GenericStereoFactor` and
`BearingFactor` take it).

**The cheirality policy** (`behind=`). A point with depth $P_z \le 0$ in the camera (the test
GTSAM's `PinholeCamera` and `StereoCamera` use) has no image:
- `"zero"` (default): GTSAM's default factor behaviour (`throwCheirality=false`): the residual is
  fixed at $2 f_x$ in every component (the value GTSAM's `GenericProjectionFactor` and
  `GenericStereoFactor` return) and every Jacobian block is zero, so a step never pulls the
  point through the image plane toward its mirror image; the point is moved only by the
  factors that see it in front. The cost jumps where the point crosses the plane, as GTSAM's.
- `"mirror"`: no check (Ceres' `SnavelyReprojectionError`, `lieax.ba`'s Snavely camera): the
  projection of $-P$ is compared with the measurement, and a solve can converge to the mirrored
  solution.
A solve does not stop for such points: after it, `count_behind(graph, result.values)` says how
many observations ended behind their camera, `behind_camera` which ones, and
`check_in_front` raises `CheiralityError` naming the factor kind and the instances (GTSAM's
`throwCheirality=true`, outside the solve). A bearing has no such policy: its error is the
angle, largest at the mirror image (`_bearing`).
"""

from collections.abc import Iterable
from typing import Any

import jax
import jax.numpy as jnp
import numpy as np
from jax.typing import ArrayLike

from .._typing import PyTree
from ..factorgraph import Factor, FactorGraph, VarRef
from ..groups import S2, SE3
from ._bearing import bearing_error, bearing_error_jacobians
from ._calibration import calibration_size, pixel
from ._frame import check_camera_inputs, in_camera
from ._pinhole import project_jacobians
from ._stereo import LAYOUT as STEREO_LAYOUT
from ._stereo import stereo_project_jacobians, stereo_values

BEHIND = ("zero", "mirror")

# the depths P_z of a batch of observations (compiled once per shape, not op by op)
_depths = jax.jit(lambda pose, point: in_camera(pose, point)[..., 2])


class CheiralityError(ValueError):
    """Observations whose point is behind its camera (`check_in_front`)."""


def _check_behind(behind, entry):
    if behind not in BEHIND:
        raise ValueError(f"{entry}: behind must be one of {BEHIND}, got {behind!r}.")


def _front(P, behind):
    """`(front, P_safe)`: the depth test $P_z > 0$ and `P` with behind points replaced by
    $(0, 0, 1)$ (so no branch divides by zero; the double-`where`), or `P` itself for
    `"mirror"`."""
    if behind == "mirror":
        return None, P
    front = P[..., 2] > 0
    unit_depth = jnp.asarray([0.0, 0.0, 1.0], dtype=P.dtype)
    return front, jnp.where(front[..., None], P, unit_depth)


def _fixed(front, residual, fx, blocks):
    """Residual $2 f_x$ and zero blocks where `front` is false (the `"zero"` policy)."""
    if front is None:
        return residual, blocks
    residual = jnp.where(front[..., None], residual, 2 * fx[..., None])
    return residual, tuple(jnp.where(front[..., None, None], b, 0.0) for b in blocks)


def projection_residual(
    T_world_camera: SE3,
    point: ArrayLike,
    measured: ArrayLike,
    calibration: ArrayLike,
    *,
    behind: str = "zero",
) -> jax.Array:
    r"""The pixel error $\kappa(P_{xy}/P_z) - u_{obs}$ of a pinhole camera (`project`) under
    the cheirality policy `behind` (module docstring), shape `(*batch, 2)`. Written with lieax
    operations (differentiable by `lieax.jacobian`); `measured` `(*batch, 2)`, `calibration`
    `(*batch, 5)` or `(*batch, 9)`."""
    _check_behind(behind, "projection_residual")
    point, measured, calibration = check_camera_inputs(
        "projection_residual", T_world_camera, point, (measured, 2, "measured", "u, v"),
        (calibration, calibration_size(calibration, "projection_residual: calibration"),
         "calibration", "Cal3_S2 or Cal3DS2"),
    )  # fmt: skip
    front, P = _front(in_camera(T_world_camera, point), behind)
    residual = pixel(calibration, P[..., :2] / P[..., 2:]) - measured
    return _fixed(front, residual, calibration[..., 0], ())[0]


def projection_residual_jacobians(
    T_world_camera: SE3,
    point: ArrayLike,
    measured: ArrayLike,
    calibration: ArrayLike,
    *,
    behind: str = "zero",
) -> tuple[jax.Array, tuple[jax.Array, jax.Array]]:
    """`(residual, (J_pose, J_point))` of `projection_residual` in closed form, blocks
    `(*batch, 2, 6)` and `(*batch, 2, 3)` (`project_jacobians`; zero behind the camera under
    `"zero"`)."""
    _check_behind(behind, "projection_residual_jacobians")
    pixel_, J_pose, J_point, _ = project_jacobians(T_world_camera, calibration, point)
    front = None if behind == "mirror" else in_camera(T_world_camera, point)[..., 2] > 0
    calibration = jnp.asarray(calibration)
    return _fixed(front, pixel_ - measured, calibration[..., 0], (J_pose, J_point))


def stereo_residual(
    T_world_camera: SE3,
    point: ArrayLike,
    measured: ArrayLike,
    calibration: ArrayLike,
    *,
    behind: str = "zero",
) -> jax.Array:
    r"""$(u_L, u_R, v) - (u_L, u_R, v)_{obs}$ of the stereo camera (`stereo_project`) under the
    cheirality policy `behind` (module docstring), shape `(*batch, 3)`; `calibration`
    `(*batch, 6)` $(f_x, f_y, s, u_0, v_0, b)$."""
    _check_behind(behind, "stereo_residual")
    point, measured, calibration = check_camera_inputs(
        "stereo_residual", T_world_camera, point, (measured, 3, "measured", "uL, uR, v"),
        (calibration, 6, "calibration", STEREO_LAYOUT),
    )  # fmt: skip
    front, P = _front(in_camera(T_world_camera, point), behind)
    return _fixed(front, stereo_values(calibration, P) - measured, calibration[..., 0], ())[0]


def stereo_residual_jacobians(
    T_world_camera: SE3,
    point: ArrayLike,
    measured: ArrayLike,
    calibration: ArrayLike,
    *,
    behind: str = "zero",
) -> tuple[jax.Array, tuple[jax.Array, jax.Array]]:
    """`(residual, (J_pose, J_point))` of `stereo_residual` in closed form, blocks
    `(*batch, 3, 6)` and `(*batch, 3, 3)`."""
    _check_behind(behind, "stereo_residual_jacobians")
    uvv, J_pose, J_point, _ = stereo_project_jacobians(T_world_camera, calibration, point)
    front = None if behind == "mirror" else in_camera(T_world_camera, point)[..., 2] > 0
    calibration = jnp.asarray(calibration)
    return _fixed(front, uvv - measured, calibration[..., 0], (J_pose, J_point))


class _CameraResidual:
    """A camera factor's residual for one instance, `(pose, point, (measured, calibration))`,
    with its closed-form `jacobian_fn` and the depth test `behind_camera` reads."""

    def __init__(self, residual, jacobians, behind):
        self.residual, self._jacobians, self.behind = residual, jacobians, behind

    def __call__(self, pose, point, data):
        return self.residual(pose, point, *data, behind=self.behind)

    def jacobians(self, pose, point, data):
        return self._jacobians(pose, point, *data, behind=self.behind)


def _camera_factor(entry, residual, pose, point, measured, calibration, size, behind, options):
    _check_behind(behind, entry)
    measured = np.asarray(measured, dtype=np.float64)
    if measured.ndim != 2 or measured.shape[1] != size:
        raise ValueError(
            f"{entry}: measured must have shape (m, {size}), one row per observation, got "
            f"{measured.shape}."
        )
    calibration = np.asarray(calibration, dtype=np.float64)
    if calibration.ndim == 1:
        calibration = calibration[None]
    if calibration.ndim != 2 or calibration.shape[0] not in (1, len(measured)):
        raise ValueError(
            f"{entry}: calibration must be one calibration or one per observation ({len(measured)}), "
            f"got shape {calibration.shape}."
        )
    calibration = np.broadcast_to(calibration, (len(measured), calibration.shape[1]))
    residual = _CameraResidual(*residual, behind)
    return Factor(
        residual,
        (pose, point),
        (jnp.asarray(measured), jnp.asarray(calibration)),
        jacobian_fn=residual.jacobians,
        **{"name": entry, **options},
    )


def projection_factor(
    pose: VarRef,
    point: VarRef,
    measured: ArrayLike,
    calibration: ArrayLike,
    *,
    behind: str = "zero",
    **options: Any,
) -> Factor:
    r"""A pinhole projection factor kind, $\kappa(P_{xy}/P_z) - u_{obs}$ (GTSAM's
    `GenericProjectionFactor<Pose3, Point3, Cal3_S2>` / `<..., Cal3DS2>` with a fixed
    calibration).

    **Arguments:**

    - `pose`, `point`: `poses[i]`, `points[j]`: an SE3 `Var` ($T_{wc}$) and a `(n, 3)` `Var`.
    - `measured`: `(m, 2)` pixels, one per observation.
    - `calibration`: `(5,)` `Cal3_S2` or `(9,)` `Cal3DS2`, shared, or `(m, 5)` / `(m, 9)`.
    - `behind`: the cheirality policy, `"zero"` (GTSAM's default) or `"mirror"` (module
      docstring).
    - `**options`: `Factor`'s (`sqrt_information`, `covariance`, `loss`, `name`...).

    ```python
    factor = cameras.projection_factor(poses[i], points[j], uv, K, sqrt_information=I2 / sigma)
    ```
    """
    calibration_size(calibration, "projection_factor: calibration")
    residual = (projection_residual, projection_residual_jacobians)
    return _camera_factor(
        "projection_factor", residual, pose, point, measured, calibration, 2, behind, options
    )


def stereo_factor(
    pose: VarRef,
    point: VarRef,
    measured: ArrayLike,
    calibration: ArrayLike,
    *,
    behind: str = "zero",
    **options: Any,
) -> Factor:
    r"""A stereo projection factor kind, $(u_L, u_R, v) - (u_L, u_R, v)_{obs}$ (GTSAM's
    `GenericStereoFactor<Pose3, Point3>`): arguments as `projection_factor`, with `measured`
    `(m, 3)` and `calibration` `(6,)` or `(m, 6)` $(f_x, f_y, s, u_0, v_0, b)$."""
    if np.shape(calibration)[-1:] != (6,):
        raise ValueError(
            "stereo_factor: calibration must have shape (6,) or (m, 6) (Cal3_S2Stereo: fx, fy, "
            f"s, u0, v0, b), got {np.shape(calibration)}."
        )
    residual = (stereo_residual, stereo_residual_jacobians)
    return _camera_factor(
        "stereo_factor", residual, pose, point, measured, calibration, 3, behind, options
    )


def bearing_factor(pose: VarRef, point: VarRef, measured: S2 | ArrayLike, **options: Any) -> Factor:
    r"""A bearing factor kind: the error $\frac{\theta}{\sin\theta} B_m^\top q$ (`bearing_error`,
    in S2's tangent, $|e| = \theta$ the angle) between the bearing $q$ of `point` from `pose`
    and `measured` (GTSAM's `BearingFactor<Pose3, Point3>`; same cost).

    **Arguments:** `pose`, `point` as `projection_factor`; `measured` an `S2` of `m` bearings in
    the camera (body) frame, or `(m, 3)` unit vectors; `**options` `Factor`'s.
    """
    if hasattr(measured, "unit_vector"):
        measured = measured.unit_vector()
    measured = jnp.asarray(measured)
    if measured.ndim != 2 or measured.shape[1] != 3:
        raise ValueError(
            f"bearing_factor: measured must be m bearings, shape (m, 3), got {measured.shape}."
        )
    return Factor(
        bearing_error,
        (pose, point),
        measured,
        jacobian_fn=_bearing_blocks,
        **{"name": "bearing_factor", **options},
    )


def _bearing_blocks(pose, point, measured):
    error, J_pose, J_point = bearing_error_jacobians(pose, point, measured)
    return error, (J_pose, J_point)


def behind_camera(
    graph: FactorGraph, values: Iterable[PyTree] | None = None
) -> dict[str, np.ndarray]:
    r"""`{factor name: (m,) bool}`: which observations of the graph's camera factors
    (`projection_factor`, `stereo_factor`) have their point behind the camera, $P_z \le 0$, at
    `values` (a solution's `values`; default the initial values). NumPy, on the host."""
    values = graph.initial_values if values is None else tuple(values)
    masks = {}
    for factor in graph.factors:
        if isinstance(factor.residual, _CameraResidual):
            poses = values[graph.index(factor.vars[0])]
            points = jnp.asarray(values[graph.index(factor.vars[1])])
            pose = poses[jnp.asarray(factor.indices[0])]
            depth = _depths(pose, points[jnp.asarray(factor.indices[1])])
            masks[factor.name] = np.asarray(depth) <= 0
    return masks


def count_behind(graph: FactorGraph, values: Iterable[PyTree] | None = None) -> int:
    """How many observations of the graph's camera factors have their point behind the camera
    at `values` (`behind_camera`; default the initial values)."""
    return int(sum(mask.sum() for mask in behind_camera(graph, values).values()))


def check_in_front(graph: FactorGraph, values: Iterable[PyTree] | None = None) -> None:
    """Raises `CheiralityError` naming each camera factor kind with observations behind the
    camera at `values` and its first instances (GTSAM's `throwCheirality=true`, checked after a
    solve); returns `None` when every point is in front."""
    bad = {name: np.flatnonzero(mask) for name, mask in behind_camera(graph, values).items()}
    bad = {name: index for name, index in bad.items() if len(index)}
    if bad:
        described = "; ".join(
            f"factor kind {name!r}: {len(index)} (instances {index[:5].tolist()}"
            f"{', ...' if len(index) > 5 else ''})"
            for name, index in bad.items()
        )
        raise CheiralityError(f"points behind the camera: {described}.")
