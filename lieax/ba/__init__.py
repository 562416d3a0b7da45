r"""Bundle adjustment building blocks: BAL files, Snavely's camera and its reprojection factor,
generated problems.

`read_bal` / `write_bal` read and write "Bundle Adjustment in the Large" files (plain or `.bz2`)
into a `BALProblem` (NumPy arrays as the file holds them; `camera_variables()` gives the cameras as
a batched `lieax.SE3` $T_{cw}$ and `(f, k_1, k_2)` intrinsics); `read_bundler` / `write_bundler`
read and write Bundler's `.out` files as the same problem (a `BundlerProblem`, with colours and
keypoint indices). `reprojection_residual` is the
residual of one camera, one point and one observation, written with lieax operations (so
`lieax.jacobian` differentiates it); `reprojection_jacobians` gives its 2×6 pose, 2×3 intrinsics
and 2×3 point blocks in closed form, the camera's tangent being the SE3 right perturbation
$(v, \omega)$ then additive $(f, k_1, k_2)$; `camera_residual` / `camera_jacobians` take the
camera as one `(pose, intrinsics)` variable with a 2×9 block, the form a factor graph's factor
takes (the camera lives in `lieax.cameras` as `snavely_*`; these are its old names, kept).
`synthetic_bal` generates problems with a ground
truth at any size (`SYNTHETIC_PRESETS`: Ladybug-49 and Trafalgar-138). Conventions: see the
docs/conventions.md (right perturbations, translation-first tangents, `T_a_b` maps b into a).
"""

from ..cameras._snavely import (
    camera_jacobians,
    camera_residual,
    project,
    reprojection_jacobians,
    reprojection_residual,
)
from ._bal import BALError, BALProblem, read_bal, write_bal
from ._bundler import BundlerProblem, read_bundler, write_bundler
from ._camera import bal_to_camera, camera_to_bal
from ._synthetic import SYNTHETIC_PRESETS, SyntheticBAL, project_numpy, synthetic_bal

__all__ = [
    "BALError",
    "BALProblem",
    "BundlerProblem",
    "SYNTHETIC_PRESETS",
    "SyntheticBAL",
    "bal_to_camera",
    "camera_jacobians",
    "camera_residual",
    "camera_to_bal",
    "project",
    "project_numpy",
    "read_bal",
    "read_bundler",
    "reprojection_jacobians",
    "reprojection_residual",
    "synthetic_bal",
    "write_bal",
    "write_bundler",
]
