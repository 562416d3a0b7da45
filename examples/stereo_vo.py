"""Stereo visual odometry as a factor graph (GTSAM's StereoVOExample, on a generated scene):
`lieax.cameras.stereo_factor` per observation, a prior on the first pose, Levenberg-Marquardt.

A rectified stereo camera (`Cal3_S2Stereo`: 700 px, 0.5 m baseline) drives forward down its
optical axis, observing landmarks 1.5-10 m beyond its last position (pixel noise 0.5 px). The
initial poses are the truth perturbed (3 cm, 1 degree) and the initial landmarks the truth plus
0.2 m, except a few initialized behind the cameras (mirrored through the first camera's centre,
as a stereo triangulation with a negative disparity puts them). GTSAM's default factor gives
their observations a fixed residual ($2 f_x$) and a zero Jacobian, so they neither move nor pull
the poses, and the solve ends with them still behind; `lieax.cameras` does the same
(`behind="zero"`, the default) and `count_behind` reports how many observations are behind
their camera before and after the solve (re-triangulate those landmarks, or drop them). With
`--behind mirror` (Ceres' Snavely convention) they are fitted through the mirrored projection
instead and move the poses. When gtsam is importable the same problem is solved with GTSAM
(`GenericStereoFactor3D`, `PriorFactorPose3`, `LevenbergMarquardtOptimizer`) and both final
costs are printed.

    python examples/stereo_vo.py [--poses 8] [--landmarks 60] [--behind zero]
"""

import argparse
import time

import jax
import jax.numpy as jnp
import numpy as np

CALIBRATION = np.array([700.0, 700.0, 0.0, 320.0, 240.0, 0.5])  # fx, fy, s, u0, v0, baseline
IMAGE = (640, 480)
PIXEL_SIGMA = 0.5  # the measurements' noise
PRIOR_SIGMA = 1e-3  # the first pose's prior (rad and m)
TOLERANCE = 1e-12  # both solvers' relative and absolute cost-decrease tolerances


def generate(poses, landmarks, behind, seed):
    """`(T_world_camera truth, points truth, camera_index, point_index, measured, initial
    poses, initial points)`: a forward drive, landmarks ahead, seen in both images."""
    from lieax import SE3, SO3, cameras

    rng = np.random.default_rng(seed)
    step = np.arange(poses)
    rotvecs = np.column_stack([0.01 * np.sin(step), 0.02 * step, np.zeros(poses)])
    positions = np.column_stack([0.2 * np.sin(0.5 * step), 0.05 * step, 0.8 * step])
    truth = SE3.from_rotation_and_translation(SO3.exp(jnp.asarray(rotvecs)), positions)
    far = positions[-1, 2]
    points = np.column_stack(
        [
            rng.uniform(-4, 4, landmarks),
            rng.uniform(-2, 2, landmarks),
            rng.uniform(far + 1.5, far + 10, landmarks),
        ]
    )
    cam, pt = (a.ravel() for a in np.meshgrid(step, np.arange(landmarks), indexing="ij"))
    uvv = np.asarray(cameras.stereo_project(truth[cam], CALIBRATION, jnp.asarray(points[pt])))
    seen = np.all((uvv[:, :2] > 0) & (uvv[:, :2] < IMAGE[0]), 1)
    seen &= (uvv[:, 2] > 0) & (uvv[:, 2] < IMAGE[1])
    seen &= np.bincount(pt[seen], minlength=landmarks)[pt] >= 2  # landmarks seen twice or more
    kept = np.unique(pt[seen])
    cam, pt, uvv, points = cam[seen], np.searchsorted(kept, pt[seen]), uvv[seen], points[kept]
    measured = uvv + rng.normal(0, PIXEL_SIGMA, uvv.shape)

    noise = np.concatenate(
        [rng.normal(0, 0.03, (poses, 3)), rng.normal(0, np.deg2rad(1.0), (poses, 3))], 1
    )
    noise[0] = 0.0  # the first pose starts at its prior
    initial_poses = truth.rplus(jnp.asarray(noise))
    initial_points = points + rng.normal(0, 0.2, points.shape)
    # behind every camera: mirrored through the first camera's centre
    initial_points[:behind] = 2 * positions[0] - initial_points[:behind]
    return truth, points, cam, pt, measured, initial_poses, initial_points


def solve_lieax(initial_poses, initial_points, cam, pt, measured, behind, max_iterations):
    """The problem in lieax: one `stereo_factor` kind and a prior on pose 0."""
    from lieax import cameras
    from lieax import factorgraph as fg
    from lieax.lstsq import Termination

    prior = initial_poses[0]
    poses = fg.Var(initial_poses, name="poses")
    points = fg.Var(jnp.asarray(initial_points), name="points")
    stereo = cameras.stereo_factor(
        poses[cam], points[pt], measured, CALIBRATION, behind=behind,
        sqrt_information=np.eye(3) / PIXEL_SIGMA,
    )  # fmt: skip
    anchor = fg.Factor(
        lambda pose: pose.rminus(prior), (poses[[0]],), sqrt_information=np.eye(6) / PRIOR_SIGMA
    )
    graph = fg.FactorGraph([stereo, anchor])
    result = graph.solve(
        termination=Termination.gtsam(
            max_iterations=max_iterations,
            function_tolerance=TOLERANCE,
            absolute_function_tolerance=TOLERANCE,
        )
    )
    return graph, result


def solve_gtsam(initial_poses, initial_points, cam, pt, measured, max_iterations):
    """The same problem in GTSAM: `GenericStereoFactor3D`, `PriorFactorPose3`, LM; its final
    cost and the number of observations behind their camera, or `None` without gtsam."""
    try:
        import gtsam
    except ImportError:
        return None
    K = gtsam.Cal3_S2Stereo(*CALIBRATION)
    pose_key, point_key = (lambda i: gtsam.symbol("x", i)), (lambda j: gtsam.symbol("l", j))
    noise = gtsam.noiseModel.Isotropic.Sigma(3, PIXEL_SIGMA)
    graph = gtsam.NonlinearFactorGraph()
    for i, j, z in zip(cam, pt, measured):
        point = gtsam.StereoPoint2(*z)
        graph.add(gtsam.GenericStereoFactor3D(point, noise, pose_key(i), point_key(j), K))
    matrices = np.asarray(initial_poses.as_matrix())
    values = gtsam.Values()
    for i, matrix in enumerate(matrices):
        values.insert(pose_key(i), gtsam.Pose3(matrix))
    for j, point in enumerate(initial_points):
        values.insert(point_key(j), np.array(point))
    prior = gtsam.noiseModel.Isotropic.Sigma(6, PRIOR_SIGMA)
    graph.add(gtsam.PriorFactorPose3(pose_key(0), gtsam.Pose3(matrices[0]), prior))
    params = gtsam.LevenbergMarquardtParams()
    params.setRelativeErrorTol(TOLERANCE)
    params.setAbsoluteErrorTol(TOLERANCE)
    params.setMaxIterations(max_iterations)
    result = gtsam.LevenbergMarquardtOptimizer(graph, values, params).optimize()
    in_front = [
        result.atPose3(pose_key(i)).transformTo(result.atPoint3(point_key(j)))[2] > 0
        for i, j in zip(cam, pt)
    ]
    return graph.error(result), int(len(in_front) - np.sum(in_front))


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--poses", type=int, default=8)
    parser.add_argument("--landmarks", type=int, default=60)
    parser.add_argument("--mirrored", type=int, default=3, help="landmarks initialized behind")
    parser.add_argument("--behind", choices=("zero", "mirror"), default="zero")
    parser.add_argument("--iterations", type=int, default=100)
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    jax.config.update("jax_enable_x64", True)
    from lieax import cameras

    truth, points, cam, pt, measured, initial_poses, initial_points = generate(
        args.poses, args.landmarks, args.mirrored, args.seed
    )
    print(
        f"{args.poses} stereo poses, {len(points)} landmarks, {len(measured)} observations, "
        f"{args.mirrored} landmarks initialized behind the cameras"
    )
    start = time.perf_counter()
    graph, result = solve_lieax(
        initial_poses, initial_points, cam, pt, measured, args.behind, args.iterations
    )
    seconds = time.perf_counter() - start
    behind_initial = cameras.count_behind(graph)
    behind_final = cameras.count_behind(graph, result.values)
    solved_poses, solved_points = result.values
    position_error = np.abs(np.asarray(solved_poses.translation() - truth.translation())).max()
    print(
        f"lieax  (behind={args.behind!r}): cost {float(result.cost):.10g} after "
        f"{int(result.iterations)} iterations ({result.status_name}, {seconds:.1f} s with "
        f"compilation); observations behind their camera: {behind_initial} at the start, "
        f"{behind_final} at the end; largest position error {position_error:.3g} m"
    )
    gtsam = solve_gtsam(initial_poses, initial_points, cam, pt, measured, args.iterations)
    # each observation behind its camera costs a constant, GTSAM's (2 fx)² per entry, whitened
    behind_cost = 0.5 * 3 * (2 * CALIBRATION[0] / PIXEL_SIGMA) ** 2
    in_front_cost = float(result.cost) - (
        behind_final * behind_cost if args.behind == "zero" else 0
    )
    relative = gtsam_cost = None
    if gtsam is not None:
        gtsam_cost, gtsam_behind = gtsam
        gtsam_in_front = gtsam_cost - gtsam_behind * behind_cost
        relative = abs(float(result.cost) - gtsam_cost) / gtsam_cost
        relative_in_front = abs(in_front_cost - gtsam_in_front) / gtsam_in_front
        print(
            f"GTSAM  (default factors):  cost {gtsam_cost:.10g}, {gtsam_behind} observations "
            f"behind their camera; relative difference {relative:.2e}"
        )
        print(
            f"without the fixed cost of the observations behind: lieax {in_front_cost:.10g}, "
            f"GTSAM {gtsam_in_front:.10g}, relative difference {relative_in_front:.2e}"
        )
    return {
        "observations": len(measured),
        "cost": float(result.cost),
        "iterations": int(result.iterations),
        "behind_initial": behind_initial,
        "behind_final": behind_final,
        "position_error": float(position_error),
        "point_error": float(np.abs(np.asarray(solved_points) - points).max()),
        "in_front_cost": in_front_cost,
        "gtsam_cost": gtsam_cost,
        "gtsam_behind": None if gtsam is None else gtsam_behind,
        "relative_difference": relative,
        "relative_difference_in_front": None if gtsam is None else relative_in_front,
    }


if __name__ == "__main__":
    main()
