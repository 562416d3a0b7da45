"""Iterative closest point (ICP) registration of point clouds, under `jit` and `vmap`.

- `point_to_point`, `point_to_plane`, `gicp` (generalized ICP, plane-to-plane): register a
  source cloud to a target, returning an `ICPResult` with `transform = T_target_source` (a
  `lieax.SE3`), `fitness`, `inlier_rmse`, `iterations` and `status`; `multi_scale` runs one of
  them coarse to fine on a voxel pyramid. `Status` is `lieax.lstsq.Status` (the one enum of every
  solver), `ICPResult` a `lieax.lstsq.SolverResult` and `ICPError` a `lieax.lstsq.SolveError`.
- `build_index`, `nearest`: the nearest-neighbour searches they use, built once per target and
  exact within a radius: `search="kdtree"` (a k-d tree in the native library, else on the host,
  called from the compiled loop, the CPU default), `"grid"` (a voxel hash grid, in JAX),
  `"brute"` (chunked brute force, for accelerators); `"auto"` chooses by backend and size.
- `estimate_normals`, `estimate_covariances`, `voxel_downsample`: preprocessing.
- `pad_clouds`: clouds of different sizes into one masked array, for `vmap` over pairs.
- `synthetic_scene`, `synthetic_pair`: generated clouds with known normals and motion.

Conventions (right perturbation, translation-first tangents, `T_a_b` maps b into a) are the
docs/conventions.md.
"""

from ._batch import pad_clouds
from ._downsample import voxel_downsample
from ._gicp import estimate_covariances, gicp
from ._grid import GridIndex
from ._host_kdtree import KDTreeIndex
from ._multiscale import multi_scale
from ._normals import estimate_normals
from ._registration import (
    ICPError,
    ICPInputError,
    ICPResult,
    Status,
    point_to_plane,
    point_to_point,
)
from ._search import SEARCHES, BruteIndex, Neighbors, build_index, nearest
from ._synthetic import synthetic_pair, synthetic_scene

__all__ = [
    "SEARCHES",
    "BruteIndex",
    "GridIndex",
    "ICPError",
    "ICPInputError",
    "ICPResult",
    "KDTreeIndex",
    "Neighbors",
    "Status",
    "build_index",
    "estimate_covariances",
    "estimate_normals",
    "gicp",
    "multi_scale",
    "nearest",
    "pad_clouds",
    "point_to_plane",
    "point_to_point",
    "synthetic_pair",
    "synthetic_scene",
    "voxel_downsample",
]
