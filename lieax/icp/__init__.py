"""Iterative closest point (ICP) registration of point clouds, under `jit` and `vmap`.

- `point_to_point`, `point_to_plane`: register a source cloud to a target, returning an
  `ICPResult` with `transform = T_target_source` (a `lieax.SE3`), `fitness`, `inlier_rmse`,
  `iterations` and `status`.
- `build_index`, `nearest`: the fixed-shape nearest-neighbour search they use (a k-d tree of
  equal leaves and a neighbour graph, built once per target; exact within a radius).
- `estimate_normals`, `voxel_downsample`: preprocessing.
- `pad_clouds`: clouds of different sizes into one masked array, for `vmap` over pairs.
- `synthetic_scene`, `synthetic_pair`: generated clouds with known normals and motion.

Conventions (right perturbation, translation-first tangents, `T_a_b` maps b into a) are the
README's "Conventions".
"""

from ._batch import pad_clouds
from ._downsample import voxel_downsample
from ._neighbors import NeighborIndex, Neighbors, build_index, nearest
from ._normals import estimate_normals
from ._registration import ICPError, ICPResult, Status, point_to_plane, point_to_point
from ._synthetic import synthetic_pair, synthetic_scene

__all__ = [
    "ICPError",
    "ICPResult",
    "NeighborIndex",
    "Neighbors",
    "Status",
    "build_index",
    "estimate_normals",
    "nearest",
    "pad_clouds",
    "point_to_plane",
    "point_to_point",
    "synthetic_pair",
    "synthetic_scene",
    "voxel_downsample",
]
