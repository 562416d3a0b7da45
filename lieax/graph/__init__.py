r"""Pose graphs, a domain package of `lieax.factorgraph` as `ba` and `imu` are: between and
prior factors, g2o and TORO files, chordal initialization, and `optimize`, a convenience.

- Factors: `between_factor(poses[i], poses[j], measured, sqrt_information=R)` and
  `prior_factor(poses[k], measured, ...)` are `lieax.factorgraph.Factor` kinds (GTSAM's
  `BetweenFactor` / `PriorFactor`) with closed-form blocks (`between_error` /
  `between_jacobians`, `prior_error` / `prior_jacobian`); `bearing_range_factor(poses[i],
  landmarks[j], bearings, ranges, sigmas=...)` is GTSAM's `BearingRangeFactor2D` / `3D`, from
  `SE2.bearing` / `range` or `SE3.bearing` / `range` (`examples/landmark_slam.py`).
- Files: `read_g2o` / `write_g2o` read and write 2D and 3D g2o files into a `PoseGraph` (poses
  as one batched `SE2`/`SE3` in file order, the file's ids in `vertex_ids`, edges as index arrays
  with measurements and square-root information); `read_toro` reads the TORO and GTSAM text
  datasets that GTSAM's `load2D`/`load3D` read (`w10000.graph`, `victoria_park.txt`), landmarks
  and bearing-range sightings included (`LandmarkGraph`).
- Initialization: `chordal_initialization` (rotations by chordal relaxation, then positions) and
  `spanning_tree_poses`.
- `to_factor_graph(graph)` is the `lieax.factorgraph.FactorGraph` of a `PoseGraph`, to add
  factors to or solve with any options; `optimize(graph)` solves it with GTSAM 4.3's
  Levenberg-Marquardt (`lieax.lstsq.LevenbergMarquardt.gtsam()`) through
  `FactorGraph.solve`, and returns an `OptimizeResult` whose `cost` is GTSAM's error
  $\tfrac12\sum r^\top\Omega r$.

The linear solver by default is a multifrontal block Cholesky with a fixed symbolic analysis
(`lieax.factorgraph`'s `CholeskyPlan`: a minimum-degree ordering of the pose graph and
supernodes, computed once per graph in NumPy with SciPy), whose numeric phase the jitted loop calls
on the host: a C++ custom call of lieax's native library, which JAX's persistent compilation cache
keeps (without that library, a NumPy host callback). Conventions: see docs/conventions.md (right
perturbations, translation-first tangents; g2o's SE3 information, ordered translation then
rotation, is used as read). Plot a graph with `lieax.viz.plot_pose_graph(graph, poses)`.
"""

from ._bearing_range import (
    bearing_range_error,
    bearing_range_factor,
    bearing_range_jacobians_2d,
    direction_error,
)
from ._factor_graph import between_factor, prior_factor, to_factor_graph
from ._factors import between_error, between_jacobians, cost, prior_error, prior_jacobian
from ._g2o import G2oError, G2oWarning, read_g2o, write_g2o
from ._graph import BetweenFactors, PoseGraph, PriorFactors, square_root_information
from ._init import chordal_initialization, spanning_tree_poses
from ._optimize import OptimizeResult, optimize
from ._toro import BearingRangeFactors, LandmarkGraph, ToroError, ToroWarning, read_toro

__all__ = [
    "BearingRangeFactors",
    "BetweenFactors",
    "G2oError",
    "G2oWarning",
    "LandmarkGraph",
    "OptimizeResult",
    "PoseGraph",
    "PriorFactors",
    "ToroError",
    "ToroWarning",
    "bearing_range_error",
    "bearing_range_factor",
    "bearing_range_jacobians_2d",
    "between_error",
    "between_factor",
    "between_jacobians",
    "chordal_initialization",
    "cost",
    "direction_error",
    "optimize",
    "prior_error",
    "prior_factor",
    "prior_jacobian",
    "read_g2o",
    "read_toro",
    "spanning_tree_poses",
    "square_root_information",
    "to_factor_graph",
    "write_g2o",
]
