"""Scan pairs of the ICP benchmarks built from the shared data: the kinds of issue 31, consecutive
scans rather than the shapes the benchmarks were tuned on.

- "LiDAR 0.25 m": consecutive outdoor laser scans (`lidar_scans_0_1_2`, scan 1 registered to scan
  0) on a 0.25 m voxel grid, 1 m correspondence distance (no reference: compare with the peer).
- "Kinect 1 cm" and "Kinect 3 cm": the Kinect office frame (`office_kinect/office1.pcd`) on a voxel
  grid (the target) against a copy resampled independently (an independent random 70% of the raw
  points on a grid shifted by half a voxel: no source point is a target point moved), cropped (the
  leftmost 5% of the view gone, as the next frame of a camera panning right would lose it) and
  moved by a known motion of consecutive frames (0.5° and 1 cm: the reference), correspondence
  distance three voxels (3 cm at 1 cm voxels, 9 cm at 3 cm).

Each pair also names the radius for the target normals (three voxels, at most 30 neighbours, as
`icp.py`'s other scans) that both libraries are given. `voxel_centroids`, `motion` and `kinect_pair`
build `neighbors.py`'s clouds too.
"""

import dataclasses
import os

import numpy as np

from lieax import read_point_cloud

LIDAR_VOXEL, LIDAR_DISTANCE = 0.25, 1.0
KINECT_VOXELS = (0.01, 0.03)
KINECT_KEEP, KINECT_CROP = 0.7, 0.05
KINECT_DEGREES, KINECT_TRANSLATION = 0.5, 0.01


@dataclasses.dataclass(frozen=True)
class ScanPair:
    """A registration problem: `source` and `target` (float64 `(n, 3)`), the maximum
    correspondence `distance`, the target normals' `normals_radius`, and `truth`
    (`T_target_source`, 4x4) where it is known, else None."""

    label: str
    source: np.ndarray
    target: np.ndarray
    distance: float
    normals_radius: float
    truth: np.ndarray | None


def voxel_centroids(points, size, offset=0.0):
    """The centroid of the points in each cell of a grid of `size`, shifted by `offset`."""
    cells = np.floor((points - offset) / size).astype(np.int64)
    _, inverse, counts = np.unique(cells, axis=0, return_inverse=True, return_counts=True)
    sums = np.zeros((counts.size, 3))
    np.add.at(sums, inverse.reshape(-1), points)
    return sums / counts[:, None]


def motion(degrees, translation, seed):
    """A 4x4 rigid motion: `degrees` about a random axis, `translation` in a random direction."""
    rng = np.random.default_rng(seed)
    axis = rng.normal(size=3)
    axis /= np.linalg.norm(axis)
    angle = np.deg2rad(degrees)
    k = np.array([[0, -axis[2], axis[1]], [axis[2], 0, -axis[0]], [-axis[1], axis[0], 0]])
    rotation = np.eye(3) + np.sin(angle) * k + (1 - np.cos(angle)) * k @ k
    direction = rng.normal(size=3)
    out = np.eye(4)
    out[:3, :3], out[:3, 3] = rotation, translation * direction / np.linalg.norm(direction)
    return out


def lidar_scans(data_dir):
    """The three consecutive LiDAR scans, `{"scan0": (n, 3), ...}` (float64)."""
    return np.load(os.path.join(data_dir, "clouds", "lidar_scans_0_1_2", "scans.npz"))


def kinect_points(data_dir):
    """The finite points of the Kinect office frame (float64 `(n, 3)`)."""
    office = read_point_cloud(os.path.join(data_dir, "clouds", "office_kinect", "office1.pcd"))
    points = np.asarray(office.points, np.float64)
    return points[np.all(np.isfinite(points), axis=1)]


def lidar_pair(data_dir, voxel=LIDAR_VOXEL, distance=LIDAR_DISTANCE):
    """Scan 1 registered to scan 0, both on a grid of `voxel`."""
    scans = lidar_scans(data_dir)
    source, target = (voxel_centroids(scans[name], voxel) for name in ("scan1", "scan0"))
    return ScanPair(f"LiDAR {voxel:g} m", source, target, distance, 3 * voxel, None)


def kinect_pair(points, voxel, distance, *, keep, crop, degrees, translation, seed, label=None):
    """The frame `points` on a grid of `voxel` (target) against a copy resampled from a random
    share `keep` of the points on a grid shifted by half a voxel, its `crop` share of smallest x
    removed, and moved by `motion(degrees, translation, seed)`, the pair's truth (source)."""
    rng = np.random.default_rng(seed)
    subset = points if keep >= 1 else points[rng.random(len(points)) < keep]
    target = voxel_centroids(points, voxel)
    resampled = voxel_centroids(subset, voxel, offset=voxel / 2)
    resampled = resampled[resampled[:, 0] > np.quantile(resampled[:, 0], crop)]
    truth = motion(degrees, translation, seed)
    source = (resampled - truth[:3, 3]) @ truth[:3, :3]  # truth maps it back onto the target
    label = label or f"Kinect {voxel * 100:g} cm"
    return ScanPair(label, source, target, distance, 3 * voxel, truth)


def scan_pairs(data_dir, kinect_voxels=KINECT_VOXELS):
    """`{label: ScanPair}`: the LiDAR pair and a Kinect pair per voxel size in `kinect_voxels`."""
    pairs = [lidar_pair(data_dir)]
    points = kinect_points(data_dir)
    for voxel in kinect_voxels:
        pairs.append(
            kinect_pair(
                points, voxel, 3 * voxel, keep=KINECT_KEEP, crop=KINECT_CROP,
                degrees=KINECT_DEGREES, translation=KINECT_TRANSLATION, seed=31,
            )
        )  # fmt: skip
    return {pair.label: pair for pair in pairs}
