r"""Camera models with closed-form Jacobians, and their factors for `lieax.factorgraph`.

| model | calibration (last axis, GTSAM's `vector()`) | measurement | functions |
|---|---|---|---|
| pinhole, `Cal3_S2` | $(f_x, f_y, s, u_0, v_0)$ | $(u, v)$ | `project`, `project_jacobians` |
| pinhole, `Cal3DS2` | $(f_x, f_y, s, u_0, v_0, k_1, k_2, p_1, p_2)$ | $(u, v)$ | the same |
| stereo, `Cal3_S2Stereo` | $(f_x, f_y, s, u_0, v_0, b)$ | $(u_L, u_R, v)$ | `stereo_project`, `stereo_project_jacobians` |
| Snavely / Bundler (BAL) | $(f, k_1, k_2)$ | $(u, v)$ | `snavely_project`, `snavely_jacobians`, ... |
| bearing | none | `S2` | `bearing`, `bearing_error`, `bearing_error_jacobians` |

Poses are `lieax.SE3`. The pinhole, stereo and bearing models take $T_{wc}$ (camera to world,
GTSAM's convention) and look down $+z$; Snavely's camera takes $T_{cw}$ (world to camera, BAL's
convention) and looks down $-z$. Every `*_jacobians` function returns the value and its blocks
in closed form: the pose block in lieax's right-perturbation tangent $(v, \omega)$ (GTSAM orders
$(\omega, v)$: `lieax.conventions.se3_jacobian_to_gtsam`), the point block, and the calibration
block in the calibration's own order. The value functions are written with lieax operations, so
`lieax.jacobian` differentiates them too (second derivatives included).

Factors: `projection_factor`, `stereo_factor`, `bearing_factor`, each one
`lieax.factorgraph.Factor`, with the cheirality policy `behind="zero"` (GTSAM's default: residual
$2 f_x$, zero Jacobian for points behind the camera) or `"mirror"` (Ceres'); `count_behind`,
`behind_camera` and `check_in_front` report points behind the camera after a solve.

```python
poses = fg.Var(SE3(...), name="poses")                        # T_world_camera
points = fg.Var(initial_points, name="points")                # (n, 3)
stereo = cameras.stereo_factor(poses[i], points[j], uLuRv, K, sqrt_information=np.eye(3))
graph = fg.FactorGraph([stereo, prior])
result = graph.solve()
cameras.count_behind(graph, result.values)                    # observations behind their camera
```
"""

from ._bearing import bearing, bearing_error, bearing_error_jacobians
from ._calibration import uncalibrate, uncalibrate_jacobians
from ._factors import (
    BEHIND,
    CheiralityError,
    bearing_factor,
    behind_camera,
    check_in_front,
    count_behind,
    projection_factor,
    projection_residual,
    projection_residual_jacobians,
    stereo_factor,
    stereo_residual,
    stereo_residual_jacobians,
)
from ._pinhole import project, project_jacobians
from ._snavely import camera_jacobians as snavely_camera_jacobians
from ._snavely import camera_residual as snavely_camera_residual
from ._snavely import project as snavely_project
from ._snavely import reprojection_jacobians as snavely_jacobians
from ._snavely import reprojection_residual as snavely_residual
from ._stereo import stereo_project, stereo_project_jacobians

__all__ = [
    "BEHIND",
    "CheiralityError",
    "bearing",
    "bearing_error",
    "bearing_error_jacobians",
    "bearing_factor",
    "behind_camera",
    "check_in_front",
    "count_behind",
    "project",
    "project_jacobians",
    "projection_factor",
    "projection_residual",
    "projection_residual_jacobians",
    "snavely_camera_jacobians",
    "snavely_camera_residual",
    "snavely_jacobians",
    "snavely_project",
    "snavely_residual",
    "stereo_factor",
    "stereo_project",
    "stereo_project_jacobians",
    "stereo_residual",
    "stereo_residual_jacobians",
    "uncalibrate",
    "uncalibrate_jacobians",
]
