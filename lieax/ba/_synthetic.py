"""Generated bundle-adjustment problems for tests and benchmarks that must run without the BAL
files: cameras orbiting a point cloud, each point tracked by a run of consecutive cameras (the
banded camera-point structure of a video sequence, closed into a loop), noisy observations, a
fraction of outliers, and a perturbed start.

`SYNTHETIC_PRESETS` holds the sizes of two BAL problems, Ladybug-49 (49 cameras, 7,776 points,
31,843 observations) and Trafalgar-138 (138 cameras, 44,033 points, 165,688 observations):
`synthetic_bal(*SYNTHETIC_PRESETS["ladybug-49"])`.
"""

import typing

import numpy as np

from ._bal import BALProblem

SYNTHETIC_PRESETS = {
    "ladybug-49": (49, 7_776, 31_843),
    "trafalgar-138": (138, 44_033, 165_688),
}


class SyntheticBAL(typing.NamedTuple):
    """A generated problem.

    **Fields:**

    - `problem`: the `BALProblem` to solve: noisy observations, perturbed cameras and points.
    - `truth`: the same observations with the true cameras and points.
    - `outliers`: `(k,)` bool, the observations replaced by outliers.
    """

    problem: BALProblem
    truth: BALProblem
    outliers: np.ndarray


def _rotation_matrices(rotvecs):
    r"""Rodrigues' formula $R = I + \frac{\sin\theta}{\theta}[\omega]_\times +
    \frac{1 - \cos\theta}{\theta^2}[\omega]_\times^2$, vectorized (rotations are ≥ 1e-3 rad
    here, so no Taylor branch is needed... but one is cheap: $\theta \to 0$ gives $I$)."""
    theta = np.linalg.norm(rotvecs, axis=-1)[..., None, None]
    safe = np.where(theta > 1e-8, theta, 1.0)
    x, y, z = rotvecs[..., 0], rotvecs[..., 1], rotvecs[..., 2]
    zero = np.zeros_like(x)
    K = np.stack([zero, -z, y, z, zero, -x, -y, x, zero], axis=-1).reshape(rotvecs.shape + (3,))
    a = np.where(theta > 1e-8, np.sin(safe) / safe, 1.0)
    b = np.where(theta > 1e-8, (1 - np.cos(safe)) / safe**2, 0.5)
    return np.eye(3) + a * K + b * (K @ K)


def project_numpy(cameras: np.ndarray, points: np.ndarray) -> tuple[np.ndarray, np.ndarray]:
    """Snavely's projection (see `lieax.ba.project`) of `points[i]` by `cameras[i]`, in NumPy:
    `(k, 9)` BAL cameras and `(k, 3)` points give `(u (k, 2), P_z (k,))`."""
    R = _rotation_matrices(cameras[:, :3])
    P = np.einsum("kij,kj->ki", R, points) + cameras[:, 3:6]
    p = -P[:, :2] / P[:, 2:]
    s = np.sum(p * p, axis=1, keepdims=True)
    f, k1, k2 = cameras[:, 6:7], cameras[:, 7:8], cameras[:, 8:9]
    return f * (1 + s * (k1 + k2 * s)) * p, P[:, 2]


def _rotvecs(R):
    r"""Rotation vectors of rotation matrices, through the quaternion of the largest of
    $4w^2, 4x^2, 4y^2, 4z^2$ (Shepperd's method, stable at every angle) with $w \ge 0$, then
    $\omega = 2\,\mathrm{atan2}(\|q_{xyz}\|, w)\, q_{xyz} / \|q_{xyz}\|$."""
    trace = np.trace(R, axis1=1, axis2=2)
    diagonal = np.stack([trace, R[:, 0, 0], R[:, 1, 1], R[:, 2, 2]], axis=1)
    pick = np.argmax(diagonal, axis=1)
    cases = np.stack(
        [
            [1 + trace, R[:, 2, 1] - R[:, 1, 2], R[:, 0, 2] - R[:, 2, 0], R[:, 1, 0] - R[:, 0, 1]],
            [
                R[:, 2, 1] - R[:, 1, 2],
                1 + 2 * R[:, 0, 0] - trace,
                R[:, 0, 1] + R[:, 1, 0],
                R[:, 0, 2] + R[:, 2, 0],
            ],
            [
                R[:, 0, 2] - R[:, 2, 0],
                R[:, 0, 1] + R[:, 1, 0],
                1 + 2 * R[:, 1, 1] - trace,
                R[:, 1, 2] + R[:, 2, 1],
            ],
            [
                R[:, 1, 0] - R[:, 0, 1],
                R[:, 0, 2] + R[:, 2, 0],
                R[:, 1, 2] + R[:, 2, 1],
                1 + 2 * R[:, 2, 2] - trace,
            ],
        ]
    )  # (case, component, n): each case is 4 q_case q (w x y z)
    q = cases[pick, :, np.arange(len(R))]
    q /= np.linalg.norm(q, axis=1, keepdims=True)
    q *= np.where(q[:, :1] < 0, -1.0, 1.0)
    norm = np.linalg.norm(q[:, 1:], axis=1, keepdims=True)
    angle = 2 * np.arctan2(norm, q[:, :1])
    scale = np.where(norm > 1e-12, angle / np.where(norm > 1e-12, norm, 1.0), 2.0)
    return scale * q[:, 1:]


def _look_at_rotvecs(centres, targets, rng, tilt):
    """Rotation vectors of $R_{cw}$ for cameras at `centres` whose $-z$ axis points at `targets`
    (BAL cameras look down $-z$), rolled and tilted by up to `tilt` rad about each axis."""
    backward = centres - targets
    z = backward / np.linalg.norm(backward, axis=1, keepdims=True)
    x = np.cross(np.array([0.0, 0.0, 1.0]), z)
    x /= np.linalg.norm(x, axis=1, keepdims=True)
    y = np.cross(z, x)
    R_world_camera = np.stack([x, y, z], axis=2)
    jitter = _rotation_matrices(rng.uniform(-tilt, tilt, (len(centres), 3)))
    return _rotvecs(np.swapaxes(R_world_camera @ jitter, 1, 2))


def _track_lengths(rng, num_cameras, num_points, num_observations):
    """Observations per point: at least 2, at most `num_cameras`, summing to `num_observations`,
    the extra ones drawn with exponential weights (many short tracks, a few long ones)."""
    lengths = np.full(num_points, 2, dtype=np.int64)
    left = num_observations - 2 * num_points
    while left > 0:
        room = lengths < num_cameras
        weights = rng.exponential(size=num_points) * room
        extra = rng.multinomial(left, weights / weights.sum())
        lengths = np.minimum(lengths + extra, num_cameras)
        left = num_observations - int(lengths.sum())
    return lengths


def synthetic_bal(
    num_cameras: int | np.integer,
    num_points: int | np.integer,
    num_observations: int | np.integer,
    *,
    noise: float = 1.0,
    outlier_fraction: float = 0.0,
    rotation_noise: float = 5e-3,
    translation_noise: float = 3e-2,
    point_noise: float = 3e-2,
    focal_length: float = 500.0,
    seed: int | None = 0,
) -> SyntheticBAL:
    r"""A generated bundle-adjustment problem with its ground truth.

    Points fill a ball of radius 1 at the origin. Cameras orbit it on a closed loop (radius about
    4, wavy in radius and height), looking at points near its centre (rolled and tilted by up to
    0.05 rad), so every point is in front of every camera ($P_z \le -2.4$, $|p| \le 0.42$, pixels
    within about ±230 at the default focal length). Each point is seen by a run of consecutive
    cameras centred on its azimuth (at least 2; lengths drawn so that they sum to
    `num_observations`), so every camera sees about `num_observations / num_cameras` points.
    Intrinsics: $f$ within 10% of `focal_length`, $k_1 \in [-0.1, 0.1]$, $k_2 \in [-0.05, 0.05]$.

    **Arguments:**

    - `num_cameras`, `num_points`, `num_observations`: sizes, with
      `2 * num_points <= num_observations <= num_cameras * num_points` and `num_cameras >= 2`.
    - `noise`: standard deviation of the pixel noise on each coordinate.
    - `outlier_fraction`: the fraction of observations replaced by pixels drawn uniformly over
      the image (the box of all true pixels).
    - `rotation_noise`, `translation_noise`, `point_noise`: standard deviations of the start's
      perturbation, added to each camera's rotation vector (rad) and translation and to each point
      (scene units; the scene is 2 across); $f$ starts 1% off, $k_1$, $k_2$ 0.01 off.
    - `focal_length`: the nominal $f$.
    - `seed`: NumPy random seed.

    **Returns:** a `SyntheticBAL` (`problem`, `truth`, `outliers`).
    """
    for name, value, least in (
        ("num_cameras", num_cameras, 2),
        ("num_points", num_points, 1),
        ("num_observations", num_observations, 1),
    ):
        if not isinstance(value, (int, np.integer)) or value < least:
            raise ValueError(f"{name} must be an integer >= {least}, got {value!r}.")
    if not 2 * num_points <= num_observations <= num_cameras * num_points:
        raise ValueError(
            "every point needs 2 to num_cameras observations: num_observations must lie in "
            f"[{2 * num_points}, {num_cameras * num_points}], got {num_observations}."
        )
    if not 0 <= outlier_fraction < 1:
        raise ValueError(f"outlier_fraction must lie in [0, 1), got {outlier_fraction}.")
    for name, value in (
        ("noise", noise),
        ("rotation_noise", rotation_noise),
        ("translation_noise", translation_noise),
        ("point_noise", point_noise),
    ):
        if not np.isfinite(value) or value < 0:
            raise ValueError(f"{name} must be finite and >= 0, got {value!r}.")
    if not np.isfinite(focal_length) or focal_length <= 0:
        raise ValueError(f"focal_length must be finite and > 0, got {focal_length!r}.")
    rng = np.random.default_rng(seed)

    direction = rng.normal(size=(num_points, 3))
    direction /= np.linalg.norm(direction, axis=1, keepdims=True)
    points = direction * rng.uniform(0, 1, (num_points, 1)) ** (1 / 3)

    angle = 2 * np.pi * (np.arange(num_cameras) + rng.uniform(-0.2, 0.2, num_cameras))
    angle /= num_cameras
    radius = 4 + 0.3 * np.sin(3 * angle)
    centres = np.stack(
        [radius * np.cos(angle), radius * np.sin(angle), 0.5 * np.sin(2 * angle)], axis=1
    )
    targets = rng.uniform(-0.1, 0.1, (num_cameras, 3))
    rotvecs = _look_at_rotvecs(centres, targets, rng, 0.05)
    R = _rotation_matrices(rotvecs)
    translations = -np.einsum("nij,nj->ni", R, centres)
    intrinsics = np.stack(
        [
            focal_length * rng.uniform(0.9, 1.1, num_cameras),
            rng.uniform(-0.1, 0.1, num_cameras),
            rng.uniform(-0.05, 0.05, num_cameras),
        ],
        axis=1,
    )
    cameras = np.concatenate([rotvecs, translations, intrinsics], axis=1)

    lengths = _track_lengths(rng, num_cameras, num_points, num_observations)
    azimuth = np.arctan2(points[:, 1], points[:, 0]) % (2 * np.pi)
    nearest = np.rint(azimuth / (2 * np.pi) * num_cameras).astype(np.int64)
    first = nearest - (lengths - 1) // 2 - rng.integers(0, 2, num_points) * (lengths % 2 == 0)
    point_indices = np.repeat(np.arange(num_points), lengths)
    starts = np.cumsum(lengths) - lengths
    step = np.arange(num_observations) - np.repeat(starts, lengths)
    camera_indices = (np.repeat(first, lengths) + step) % num_cameras

    pixels, _ = project_numpy(cameras[camera_indices], points[point_indices])
    observations = pixels + rng.normal(scale=noise, size=pixels.shape) if noise else pixels.copy()
    outliers = np.zeros(num_observations, dtype=bool)
    count = int(round(outlier_fraction * num_observations))
    if count:
        outliers[rng.choice(num_observations, count, replace=False)] = True
        half = np.max(np.abs(pixels), axis=0)
        observations[outliers] = rng.uniform(-half, half, (count, 2))

    start_cameras = cameras.copy()
    start_cameras[:, :3] += rng.normal(scale=rotation_noise, size=(num_cameras, 3))
    start_cameras[:, 3:6] += rng.normal(scale=translation_noise, size=(num_cameras, 3))
    start_cameras[:, 6] *= 1 + 0.01 * rng.choice([-1.0, 1.0], num_cameras)
    start_cameras[:, 7:] += 0.01 * rng.choice([-1.0, 1.0], (num_cameras, 2))
    start_points = points + rng.normal(scale=point_noise, size=points.shape)

    truth = BALProblem(camera_indices, point_indices, observations, cameras, points)
    problem = truth.with_parameters(start_cameras, start_points)
    return SyntheticBAL(problem=problem, truth=truth, outliers=outliers)
