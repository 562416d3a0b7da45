"""Bundle adjustment of a BAL problem with `lieax.factorgraph` and `lieax.ba`.

Cameras (Snavely's model: a pose `T_camera_world` and intrinsics `(f, k1, k2)`, 9 tangent
coordinates) and points are two variable kinds; one reprojection factor per observation, with
its closed-form Jacobian blocks (`lieax.ba.camera_jacobians`); the points are eliminated by the
Schur complement and the reduced camera system is solved by the host sparse Cholesky.

By default the problem is generated (`lieax.ba.synthetic_bal`: cameras around a cloud of points,
1 px noise, a perturbed start); `--preset ladybug-49` / `trafalgar-138` generates one at the size
of those BAL sets, `--bal problem-*.txt[.bz2]` reads a real one, `--write out.txt` writes the
solved problem in BAL format.

    python examples/bundle_adjustment.py
    python examples/bundle_adjustment.py --preset ladybug-49 --loss huber --outliers 0.05
"""

import argparse
import time

import jax
import jax.numpy as jnp
import numpy as np

from lieax import ba, lstsq
from lieax import factorgraph as fg

jax.config.update("jax_enable_x64", True)


def reprojection_errors(problem):
    """`(rmse, median)` of the reprojection errors (pixels) of a `BALProblem` as it stands; the
    median is the robust figure when some observations are outliers."""
    projected, _ = ba.project_numpy(
        problem.cameras[problem.camera_indices], problem.points[problem.point_indices]
    )
    errors = np.linalg.norm(projected - problem.observations, axis=1)
    return float(np.sqrt(np.mean(errors**2))), float(np.median(errors))


def solve(problem, *, loss=None, max_iterations=50, verbose=False):
    """Bundle-adjusts `problem`; returns the solved `BALProblem` and the solver's result."""
    pose, intrinsics = problem.camera_variables(jnp.float64)
    cameras = fg.Var((pose, intrinsics), name="cameras")
    points = fg.Var(jnp.asarray(problem.points), name="points")
    reprojection = fg.Factor(
        ba.camera_residual,
        (cameras[problem.camera_indices], points[problem.point_indices]),
        jnp.asarray(problem.observations),
        loss=loss,
        jacobian_fn=ba.camera_jacobians,
        name="reprojection",
    )
    # The gauge (a similarity of the whole scene) is left free, as in Ceres' and GTSAM's BAL
    # examples: the damping keeps the steps finite.
    graph = fg.FactorGraph([reprojection], check_gauge=False)
    # The Marquardt diagonal (Ceres' damping) with Nielsen's λ rule: GTSAM's ×10 / ÷10 with it
    # rejects about every other step.
    result = graph.solve(
        eliminate=points,
        solver=lstsq.LevenbergMarquardt.gtsam(scaling="clipped", damping_update="nielsen"),
        termination=lstsq.Termination.gtsam(max_iterations=max_iterations),
        verbose=verbose,
    )
    (pose, intrinsics), solved_points = result.values
    solved = problem.with_parameters(
        np.asarray(ba.camera_to_bal(pose, intrinsics)), np.asarray(solved_points)
    )
    return solved, result


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    source = parser.add_mutually_exclusive_group()
    source.add_argument("--bal", help="a BAL problem file (.txt or .txt.bz2)")
    source.add_argument("--preset", choices=sorted(ba.SYNTHETIC_PRESETS))
    parser.add_argument("--cameras", type=int, default=8, help="generated problem: cameras")
    parser.add_argument("--points", type=int, default=150, help="generated problem: points")
    parser.add_argument("--observations", type=int, default=900)
    parser.add_argument("--outliers", type=float, default=0.0, help="fraction of outliers")
    parser.add_argument("--loss", choices=("trivial", "huber"), default="trivial")
    parser.add_argument("--huber", type=float, default=2.0, help="Huber threshold, pixels")
    parser.add_argument("--iterations", type=int, default=50)
    parser.add_argument("--write", help="write the solved problem to this BAL file")
    parser.add_argument("--verbose", action="store_true")
    args = parser.parse_args(argv)

    truth = None
    if args.bal:
        problem = ba.read_bal(args.bal)
    else:
        sizes = (
            ba.SYNTHETIC_PRESETS[args.preset]
            if args.preset
            else (args.cameras, args.points, args.observations)
        )
        generated = ba.synthetic_bal(*sizes, outlier_fraction=args.outliers, seed=0)
        problem, truth = generated.problem, generated.truth
    print(
        f"{problem.num_cameras} cameras, {problem.num_points} points, "
        f"{problem.num_observations} observations"
    )
    loss = lstsq.Huber(args.huber) if args.loss == "huber" else None

    start = time.perf_counter()
    solved, result = solve(problem, loss=loss, max_iterations=args.iterations, verbose=args.verbose)
    seconds = time.perf_counter() - start
    summary = {"status": result.status_name, "iterations": int(result.iterations)}
    summary["initial_rmse"], summary["initial_median"] = reprojection_errors(problem)
    summary["rmse"], summary["median"] = reprojection_errors(solved)
    if truth is not None:
        summary["truth_rmse"], summary["truth_median"] = reprojection_errors(truth)
    print(
        f"{summary['status']} after {summary['iterations']} iterations in {seconds:.2f} s "
        "(first call: structure analysis and compilation included)"
    )
    print("reprojection error (px)    RMSE   median")
    rows = [("start", "initial_"), ("solved", "")]
    rows += [("true cameras and points", "truth_")] if truth is not None else []
    for label, key in rows:
        print(f"  {label:24s} {summary[key + 'rmse']:6.3f} {summary[key + 'median']:8.3f}")
    if args.write:
        ba.write_bal(args.write, solved)
        print(f"wrote {args.write}")
    return summary


if __name__ == "__main__":
    main()
