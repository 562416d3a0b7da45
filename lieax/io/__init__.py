"""Reading and writing point clouds (PLY, PCD, NumPy arrays) on the host, with NumPy only."""

from ._common import PointCloudData, PointCloudFileError
from ._pcd import read_pcd, write_pcd
from ._ply import read_ply, write_ply
from ._pointcloud import read_point_cloud

__all__ = [
    "PointCloudData",
    "PointCloudFileError",
    "read_pcd",
    "read_ply",
    "read_point_cloud",
    "write_pcd",
    "write_ply",
]
