"""Reading and writing point clouds (PLY, PCD, NumPy arrays) on the host, with NumPy only."""

from ._pointcloud import (
    PointCloudData,
    read_pcd,
    read_ply,
    read_point_cloud,
    write_pcd,
    write_ply,
)

__all__ = ["PointCloudData", "read_pcd", "read_ply", "read_point_cloud", "write_pcd", "write_ply"]
