r"""Pose graphs: g2o files, between and prior factors, Levenberg-Marquardt on block-sparse normal
equations.

`read_g2o` / `write_g2o` read and write 2D and 3D g2o files into a `PoseGraph` (poses as one
batched `SE2`/`SE3` in file order, the file's ids in `vertex_ids`, edges as index arrays with
measurements and square-root information); `read_toro` reads the TORO and GTSAM text datasets
that GTSAM's `load2D`/`load3D` read (`w10000.graph`, `victoria_park.txt`), landmarks and
bearing-range sightings included (`LandmarkGraph`). `optimize` runs Levenberg-Marquardt with GTSAM's
semantics (the pose graph as a `lieax.factorgraph.FactorGraph` of between and prior factors,
solved by its loop) and returns an `OptimizeResult` whose `cost` is GTSAM's error $\tfrac12\sum r^\top\Omega r$.

The linear solver by default is a multifrontal block Cholesky with a fixed symbolic analysis
(`CholeskyPlan`: a minimum-degree ordering of the pose graph and supernodes, computed once per
graph in numpy with SciPy, which JAX already depends on), whose numeric phase the jitted loop
calls on the host (a C++ custom call of lieax's native library, which JAX's persistent
compilation cache keeps; without that library a NumPy host callback); `solver="cg"` keeps everything in JAX (block-Jacobi preconditioned
conjugate gradients) for accelerators. Conventions: see docs/conventions.md (right
perturbations, translation-first tangents; g2o's SE3 information, ordered translation then
rotation, is used as read). Plot a graph with `lieax.viz.plot_pose_graph(graph, poses)`.

Landmarks: `bearing_range_factor(poses[i], landmarks[j], bearings, ranges, sigmas=...)` is a
`lieax.factorgraph.Factor` kind of bearing-range sightings (GTSAM's `BearingRangeFactor2D` /
`3D`), from `SE2.bearing` / `range` (the bearing residual wrapped, $\mathrm{Log}(Z^{-1}\hat Z)$)
or `SE3.bearing` / `range`; add it to the factors of `to_factor_graph` or of a graph of your own
(`examples/landmark_slam.py`).
"""

from ..factorgraph._sparse import BlockPattern, CholeskyPlan, block_matvec, pcg
from ._bearing_range import (
    bearing_range_error,
    bearing_range_factor,
    bearing_range_jacobians_2d,
    direction_error,
)
from ._factor_graph import to_factor_graph
from ._factors import between_error, between_jacobians, cost, prior_error, prior_jacobian
from ._g2o import G2oError, G2oWarning, read_g2o, write_g2o
from ._graph import BetweenFactors, PoseGraph, PriorFactors, square_root_information
from ._init import chordal_initialization, spanning_tree_poses
from ._optimize import OptimizeResult, Status, optimize
from ._toro import BearingRangeFactors, LandmarkGraph, ToroError, ToroWarning, read_toro

__all__ = [
    "BearingRangeFactors",
    "BetweenFactors",
    "BlockPattern",
    "CholeskyPlan",
    "G2oError",
    "G2oWarning",
    "LandmarkGraph",
    "OptimizeResult",
    "PoseGraph",
    "PriorFactors",
    "Status",
    "ToroError",
    "ToroWarning",
    "bearing_range_error",
    "bearing_range_factor",
    "bearing_range_jacobians_2d",
    "between_error",
    "between_jacobians",
    "block_matvec",
    "chordal_initialization",
    "cost",
    "direction_error",
    "optimize",
    "pcg",
    "prior_error",
    "prior_jacobian",
    "read_g2o",
    "read_toro",
    "spanning_tree_poses",
    "square_root_information",
    "to_factor_graph",
    "write_g2o",
]
