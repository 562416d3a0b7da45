"""2D landmark SLAM with `lieax.factorgraph`: a robot's poses and the landmarks it sees, from
odometry and bearing-range sightings (GTSAM's `PlanarSLAMExample`, at the size of a short drive).

The robot drives a meandering loop through a field of landmarks; at each pose it measures its
motion since the last one (odometry, 5 cm and 1 degree of noise) and the bearing and range of
the landmarks within 8 m (3 degrees, 10 cm). The graph is a prior on the first pose, one
between factor per step and one `lieax.graph.bearing_range_factor` per sighting:

    factors = [
        Factor(graph.prior_error, (poses[[0]],), first_pose, sqrt_information=prior_root),
        Factor(graph.between_error, (poses[i], poses[j]), odometry, sqrt_information=odometry_root),
        graph.bearing_range_factor(poses[k], landmarks[l], bearings, ranges, sigmas=(0.05, 0.1)),
    ]
    result = FactorGraph(factors).solve()

The start is dead reckoning (the odometry composed) and each landmark placed from its first
sighting. When GTSAM is installed, the same problem (`PriorFactorPose2`, `BetweenFactorPose2`,
`BearingRangeFactor2D`, Levenberg-Marquardt) is solved by GTSAM too, and both final costs are
printed.

    python examples/landmark_slam.py [--poses 300] [--landmarks 60] [--seed 0]
"""

import argparse
import time

import jax
import numpy as np

ODOMETRY_SIGMAS = np.array([0.05, 0.05, np.deg2rad(1.0)])  # x, y (m), heading (rad)
PRIOR_SIGMAS = np.array([0.01, 0.01, np.deg2rad(0.1)])
BEARING_SIGMA, RANGE_SIGMA = np.deg2rad(3.0), 0.1
MAX_RANGE = 8.0  # m


def simulate(poses, landmarks, rng):
    """The truth and the measurements of a drive: a dict with `truth_poses` `(n, 3)` rows
    `(x, y, theta)`, `truth_landmarks` `(L, 2)`, `odometry` `(n - 1, 3)` (each step in the frame of
    the pose it starts from, noisy), and the sightings `pose_index`, `landmark_index`, `bearings`
    (radians, in the robot's frame), `ranges` (noisy)."""
    step = 0.5  # m per pose
    radius = step * poses / (2 * np.pi)  # a loop of `poses` steps, meandering around a circle
    angle = 2 * np.pi * np.arange(poses + 1) / poses
    wiggle = 0.25 * radius * np.sin(5 * angle)
    xy = np.stack([(radius + wiggle) * np.cos(angle), (radius + wiggle) * np.sin(angle)], 1)
    heading = np.arctan2(*np.flip(np.diff(xy, axis=0), axis=1).T)
    truth = np.concatenate([xy[:-1], heading[:, None]], axis=1)
    # landmarks beside the path (within 6 m of a random pose), so that every one is seen
    near = truth[rng.integers(0, poses, size=landmarks), :2]
    truth_landmarks = near + rng.uniform(-6.0, 6.0, size=(landmarks, 2)) / np.sqrt(2)

    relative = np.array([_between(truth[k], truth[k + 1]) for k in range(poses - 1)])
    odometry = relative + rng.normal(size=relative.shape) * ODOMETRY_SIGMAS
    offsets = truth_landmarks[None, :, :] - truth[:, None, :2]  # (n, L, 2)
    distance = np.linalg.norm(offsets, axis=-1)
    pose_index, landmark_index = np.nonzero(distance < MAX_RANGE)
    seen = offsets[pose_index, landmark_index]
    bearings = np.arctan2(seen[:, 1], seen[:, 0]) - truth[pose_index, 2]
    bearings = np.angle(np.exp(1j * (bearings + rng.normal(size=len(seen)) * BEARING_SIGMA)))
    ranges = distance[pose_index, landmark_index] + rng.normal(size=len(seen)) * RANGE_SIGMA
    return {
        "truth_poses": truth,
        "truth_landmarks": truth_landmarks,
        "odometry": odometry,
        "pose_index": pose_index,
        "landmark_index": landmark_index,
        "bearings": bearings,
        "ranges": ranges,
    }


def _between(a, b):
    """`(x, y, theta)` of $A^{-1} B$ for poses given as `(x, y, theta)` (NumPy)."""
    c, s = np.cos(a[2]), np.sin(a[2])
    dx, dy = b[0] - a[0], b[1] - a[1]
    return np.array([c * dx + s * dy, -s * dx + c * dy, np.angle(np.exp(1j * (b[2] - a[2])))])


def initial_guess(data):
    """Dead reckoning from the first true pose, and each seen landmark placed from its first
    sighting (`(poses (n, 3), landmarks (L, 2))`; a landmark never seen stays at the origin)."""
    poses = [data["truth_poses"][0]]
    for x, y, theta in data["odometry"]:
        px, py, ptheta = poses[-1]
        c, s = np.cos(ptheta), np.sin(ptheta)
        poses.append(np.array([px + c * x - s * y, py + s * x + c * y, ptheta + theta]))
    poses = np.array(poses)
    landmarks = np.zeros_like(data["truth_landmarks"])
    order = np.argsort(data["pose_index"], kind="stable")
    seen = set()
    for k in order:
        j = data["landmark_index"][k]
        if j in seen:
            continue
        seen.add(j)
        x, y, theta = poses[data["pose_index"][k]]
        angle = theta + data["bearings"][k]
        landmarks[j] = [
            x + data["ranges"][k] * np.cos(angle),
            y + data["ranges"][k] * np.sin(angle),
        ]
    return poses, landmarks


def solve_lieax(data, start_poses, start_landmarks):
    """The graph in `lieax.factorgraph` and its solve (GTSAM's Levenberg-Marquardt defaults):
    returns `(result, poses Var, landmarks Var)`."""
    import jax.numpy as jnp

    from lieax import SE2, graph
    from lieax.factorgraph import Factor, FactorGraph, Var

    def se2(rows):
        rows = jnp.asarray(rows)
        return SE2.from_xy_theta(rows[:, 0], rows[:, 1], rows[:, 2])

    poses = Var(se2(start_poses), name="poses")
    landmarks = Var(jnp.asarray(start_landmarks), name="landmarks")
    n = len(start_poses)
    i, j = np.arange(n - 1), np.arange(1, n)
    factors = [
        Factor(
            graph.prior_error,
            (poses[[0]],),
            se2(data["truth_poses"][:1]),
            sqrt_information=np.diag(1 / PRIOR_SIGMAS),
            name="prior",
        ),
        Factor(
            graph.between_error,
            (poses[i], poses[j]),
            se2(data["odometry"]),
            sqrt_information=np.diag(1 / ODOMETRY_SIGMAS),
            name="odometry",
        ),
        graph.bearing_range_factor(
            poses[data["pose_index"]],
            landmarks[data["landmark_index"]],
            data["bearings"],
            data["ranges"],
            sigmas=(BEARING_SIGMA, RANGE_SIGMA),
        ),
    ]
    return FactorGraph(factors).solve(), poses, landmarks


def solve_gtsam(data, start_poses, start_landmarks):
    """The same graph in GTSAM, solved by its Levenberg-Marquardt with default parameters:
    `(initial error, final error, iterations)`."""
    import gtsam

    def x(k):
        return gtsam.symbol("x", int(k))

    def landmark(k):
        return gtsam.symbol("l", int(k))

    factors = gtsam.NonlinearFactorGraph()
    factors.add(
        gtsam.PriorFactorPose2(
            x(0),
            gtsam.Pose2(*data["truth_poses"][0]),
            gtsam.noiseModel.Diagonal.Sigmas(PRIOR_SIGMAS),
        )
    )
    odometry_noise = gtsam.noiseModel.Diagonal.Sigmas(ODOMETRY_SIGMAS)
    for k, step in enumerate(data["odometry"]):
        factors.add(gtsam.BetweenFactorPose2(x(k), x(k + 1), gtsam.Pose2(*step), odometry_noise))
    sighting_noise = gtsam.noiseModel.Diagonal.Sigmas(np.array([BEARING_SIGMA, RANGE_SIGMA]))
    for k, j, bearing, distance in zip(
        data["pose_index"], data["landmark_index"], data["bearings"], data["ranges"]
    ):
        factors.add(
            gtsam.BearingRangeFactor2D(
                x(k), landmark(j), gtsam.Rot2.fromAngle(bearing), distance, sighting_noise
            )
        )
    values = gtsam.Values()
    for k, pose in enumerate(start_poses):
        values.insert(x(k), gtsam.Pose2(*pose))
    for j in np.unique(data["landmark_index"]):
        values.insert(landmark(j), start_landmarks[j])
    optimizer = gtsam.LevenbergMarquardtOptimizer(factors, values)
    result = optimizer.optimize()
    return factors.error(values), factors.error(result), optimizer.iterations()


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--poses", type=int, default=300)
    parser.add_argument("--landmarks", type=int, default=60)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    jax.config.update("jax_enable_x64", True)

    data = simulate(args.poses, args.landmarks, np.random.default_rng(args.seed))
    start_poses, start_landmarks = initial_guess(data)
    seen = np.unique(data["landmark_index"])
    print(
        f"{args.poses} poses, {len(seen)} of {args.landmarks} landmarks seen, "
        f"{len(data['bearings'])} bearing-range sightings"
    )
    start = time.perf_counter()
    result, _, _ = solve_lieax(data, start_poses, start_landmarks)
    elapsed = time.perf_counter() - start
    solved_poses, solved_landmarks = result.values
    xy_theta = np.asarray(solved_poses.as_xy_theta())
    position_rms = np.sqrt(np.mean(np.sum((xy_theta[:, :2] - data["truth_poses"][:, :2]) ** 2, 1)))
    start_rms = np.sqrt(np.mean(np.sum((start_poses[:, :2] - data["truth_poses"][:, :2]) ** 2, 1)))
    landmark_error = np.asarray(solved_landmarks)[seen] - data["truth_landmarks"][seen]
    landmark_rms = np.sqrt(np.mean(np.sum(landmark_error**2, axis=1)))
    history = np.asarray(result.cost_history)
    print(
        f"lieax: cost {history[0]:.6f} -> {float(result.cost):.10f}, {result.status_name} after "
        f"{int(result.iterations)} iterations, {elapsed:.2f} s (with compilation)"
    )
    print(
        f"position rms {start_rms:.3f} m (dead reckoning) -> {position_rms:.3f} m, "
        f"landmark rms {landmark_rms:.3f} m"
    )
    summary = {
        "status": result.status_name,
        "initial_cost": float(history[0]),
        "cost": float(result.cost),
        "position_rms": float(position_rms),
        "start_position_rms": float(start_rms),
        "landmark_rms": float(landmark_rms),
        "gtsam_cost": None,
    }
    try:
        import gtsam  # noqa: F401
    except ImportError:
        print("GTSAM is not installed: no comparison")
        return summary
    initial_error, final_error, iterations = solve_gtsam(data, start_poses, start_landmarks)
    difference = abs(final_error - float(result.cost)) / final_error
    print(
        f"GTSAM: cost {initial_error:.6f} -> {final_error:.10f} after {iterations} iterations; "
        f"the final costs differ by {difference:.1e} relative"
    )
    summary.update(gtsam_initial_cost=initial_error, gtsam_cost=final_error)
    return summary


if __name__ == "__main__":
    main()
