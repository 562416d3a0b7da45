r"""Bundle adjustment on a BAL problem: Ceres (pyceres), GTSAM 4.3 and `lieax.factorgraph` from the
same start, with the same iteration cap and loss.

Needs the `bench` extra (pyceres, GTSAM 4.3). The problem is a generated one at the size of a BAL
problem (`lieax.ba.SYNTHETIC_PRESETS`: `ladybug-49`, `trafalgar-138`) or a real
`problem-*.txt(.bz2)` file:

    python benchmarks/ba.py [--problem ladybug-49|trafalgar-138|PATH] [--iterations 20]
                            [--loss trivial|huber] [--huber-delta 2.0] [--outliers 0.0]
                            [--solvers ceres,ceres-colmap,gtsam,gtsam-schur,lieax,
                                       lieax-gtsam-rule]
                            [--lieax-damping identity|marquardt]
                            [--lieax-lambda-update nielsen|gtsam] [--rounds 1]

Every solver minimizes $\tfrac12\sum_i \rho(\|u_i - u_{obs,i}\|^2)$ over Snavely's camera
(`lieax.ba.project`; Huber $\rho$ as Ceres' `HuberLoss(δ)` and GTSAM's `mEstimator.Huber(δ)`),
without a gauge prior (both damp the 7 gauge directions). The table's costs are recomputed here
with one NumPy function from each solver's final cameras and points, so they compare; the last
column is the solver's own figure. They differ where GTSAM moved points behind a camera:
`GeneralSFMFactor` catches GTSAM's `CheiralityException` and returns a zero error there, so its
LM can lower its cost by pushing points behind cameras (with a robust loss and outliers, measured
here, plain LM ends with almost every point behind), where Snavely's model (and Ceres) projects
them mirrored.

- **Ceres (Python cost)**: `pyceres` 2.6 ships no C++ reprojection cost (its `pyceres.factors`
  has only `NormalError` and `NormalPrior`), so the Snavely cost is a Python `CostFunction` with
  closed-form Jacobians, camera as BAL's 9-vector (additive angle-axis, as Ceres' `bundle_adjuster`
  example), `SPARSE_SCHUR`, Levenberg-Marquardt, Ceres' default tolerances and threads (1). A
  Python call costs about 20 µs here (Ceres' evaluation time over the calls on Ladybug-49): the
  column "Ceres w/o eval." subtracts Ceres' own residual and Jacobian evaluation times.
- **Ceres (C++ cost via pycolmap)** (`ceres-colmap`, needs `pip install pycolmap`, 4.2.1 here,
  which links Ceres 2.2): COLMAP's C++ autodiff `ReprojErrorCost` for its `RADIAL` camera
  $(f, c_x, c_y, k_1, k_2)$, $u = f(1 + k_1|q|^2 + k_2|q|^4)q + c$ with $q = Q_{xy}/Q_z$. Snavely's
  camera is that one with $c = 0$ (held constant) after $R_x(\pi)$: $Q = R_x(\pi)P$ has
  $Q_{xy}/Q_z = (p_x, -p_y)$, so the pose is $(R_x(\pi)R, R_x(\pi)t)$ and the observation
  $(u_x, -u_y)$. The problem is a `pycolmap.Reconstruction` (one camera, trivial rig and frame per
  BAL camera) whose Ceres problem COLMAP's `create_default_ceres_bundle_adjuster` builds (pose a
  quaternion and translation on COLMAP's product manifold, intrinsics with $c$ constant, no gauge
  fixed); it is solved with `pyceres.solve` and the same options as the Python-cost run
  (`SPARSE_SCHUR`, LM, default tolerances and threads). The cost at the start is checked against
  the NumPy one to 1e-9 relative before anything is timed (from the residuals, and Ceres' own
  figure with COLMAP's loss). The camera's tangent (quaternion manifold) differs from the additive
  angle-axis of the Python-cost run, so the two take different steps. COLMAP's cost returns a zero
  residual for a point behind its camera (as GTSAM's below); the note counts them where the
  costs differ.
- **GTSAM**: `GeneralSFMFactor` with `PinholeCamera<Cal3Bundler>` (as GTSAM's
  `SFMExample_bal.py`, the camera converted from BAL's $-z$-looking convention like `readBal`, but
  in double precision: `readBal` parses with `float`), unit noise, `LevenbergMarquardtOptimizer`
  with default parameters (multifrontal Cholesky, COLAMD) and the iteration cap; `gtsam-schur` is
  4.3's `SfmLevenbergMarquardtOptimizer` with `SfmEliminationMode.Schur` (points eliminated
  first, as Ceres' Schur complement) and `SfmLevenbergMarquardtParams.ceresDefaults()` (its
  default parameters raise an empty `RuntimeError` on these problems).
- **lieax**: `lieax.factorgraph` with `lieax.ba.camera_residual` and the closed-form
  `lieax.ba.camera_jacobians`, points eliminated by the Schur complement, LM damped by the clipped
  diagonal of $J^\top J$ as Ceres (`--lieax-damping identity` for GTSAM's $\lambda I$, which
  stalls on Trafalgar-size problems as GTSAM's own LM does) and, by default, Ceres'
  `LevenbergMarquardtStrategy` for the damping (`damping_update="nielsen"`: $\lambda_0 = 10^{-4}$,
  Ceres' `1 / initial_trust_region_radius`; on success $\lambda \leftarrow \lambda
  \max(\tfrac13, 1 - (2\rho - 1)^3)$, on failure $\lambda \leftarrow \lambda\nu$,
  $\nu \leftarrow 2\nu$; `--lieax-lambda-update gtsam` for GTSAM's ×10 / ÷10 from $10^{-5}$,
  which rejected 21 of 41 tries on synthetic ladybug-49 with Huber and 5% outliers, against 12 of
  32 with Ceres' rule); a warm solve is timed, the first call (analysis and
  compilation) and the linear solves are in the notes.

Iterations are not counted alike: Ceres counts every step tried (successful or not), GTSAM one
per outer LM iteration (which may try several λ); lieax as GTSAM (its linear solves, rejected
steps included, are in the notes). `--rounds R` runs every solver R times, interleaved, and
reports the median. `lieax-gtsam-rule` is lieax with GTSAM's λ rule (same damping). The
process pins itself to one CPU before the libraries start their thread pools (`LIEAX_BENCH_PIN=0` leaves it unpinned), as `pgo.py`.
"""

import argparse
import math
import os
import sys

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import _environment

_environment.one_core()

import dataclasses
import statistics
import time

import jax

jax.config.update("jax_enable_x64", True)

import numpy as np
from _timing import format_seconds, machine_description, markdown_table

from lieax import ba


@dataclasses.dataclass(frozen=True)
class Run:
    """One solver's run: wall time of the solve, iterations as the solver counts them, costs
    recomputed by `cost`, the final cost as the solver reports it, and an optional note."""

    solver: str
    total_s: float
    iterations: int
    initial_cost: float
    final_cost: float
    own_final_cost: float
    without_evaluation_s: float = math.nan
    note: str = ""


def load_problem(spec, *, outliers=0.0, seed=0):
    """`(name, BALProblem)`: a synthetic preset by name, or a BAL file by path."""
    if spec in ba.SYNTHETIC_PRESETS:
        generated = ba.synthetic_bal(
            *ba.SYNTHETIC_PRESETS[spec], outlier_fraction=outliers, seed=seed
        )
        return f"synthetic {spec}", generated.problem
    return os.path.basename(spec), ba.read_bal(spec)


def cost(problem, cameras, points, loss="trivial", delta=1.0):
    r"""$\tfrac12\sum\rho(\|r\|^2)$ with Ceres' convention for $\rho$ (trivial: $s$; Huber:
    $s$ below $\delta^2$, $2\delta\sqrt s - \delta^2$ above)."""
    u, _ = ba.project_numpy(cameras[problem.camera_indices], points[problem.point_indices])
    s = np.sum((u - problem.observations) ** 2, axis=1)
    if loss == "huber":
        s = np.where(s <= delta**2, s, 2 * delta * np.sqrt(s) - delta**2)
    return 0.5 * float(np.sum(s))


# --- Ceres -------------------------------------------------------------------------------


def _snavely_cost_class():
    import pyceres

    class SnavelyCost(pyceres.CostFunction):
        r"""Snavely's residual for a BAL 9-vector camera (additive angle-axis) and a point, with
        closed-form Jacobians: $\partial P/\partial\omega = -R[X]_\times J_r(\omega)$,
        $\partial P/\partial t = I$, $\partial P/\partial X = R$, then the chain of
        `lieax.ba.reprojection_jacobians`."""

        def __init__(self, observed):
            super().__init__()
            self.set_num_residuals(2)
            self.set_parameter_block_sizes([9, 3])
            self.u_obs, self.v_obs = observed

        def Evaluate(self, parameters, residuals, jacobians):
            wx, wy, wz, tx, ty, tz, f, k1, k2 = parameters[0].tolist()
            X, Y, Z = parameters[1].tolist()
            theta2 = wx * wx + wy * wy + wz * wz
            if theta2 > 1e-16:
                theta = math.sqrt(theta2)
                sin, cos = math.sin(theta), math.cos(theta)
                a, b, e = sin / theta, (1 - cos) / theta2, (theta - sin) / (theta2 * theta)
            else:
                a, b, e = 1.0, 0.5, 1 / 6
            # R = I + a K + b K², K = [ω]×
            K = (0.0, -wz, wy, wz, 0.0, -wx, -wy, wx, 0.0)
            K2 = _mul(K, K)
            R = tuple((1.0 if i % 4 == 0 else 0.0) + a * K[i] + b * K2[i] for i in range(9))
            Px = R[0] * X + R[1] * Y + R[2] * Z + tx
            Py = R[3] * X + R[4] * Y + R[5] * Z + ty
            Pz = R[6] * X + R[7] * Y + R[8] * Z + tz
            inverse_depth = 1 / Pz
            px, py = -Px * inverse_depth, -Py * inverse_depth
            s = px * px + py * py
            radial = 1 + s * (k1 + k2 * s)
            residuals[0] = f * radial * px - self.u_obs
            residuals[1] = f * radial * py - self.v_obs
            if jacobians is None:
                return True
            # du/dP = du/dp · dp/dP, dp/dP = -(1/P_z) [I | p]
            c = 2 * (k1 + 2 * k2 * s)
            d00, d01, d11 = f * (radial + c * px * px), f * c * px * py, f * (radial + c * py * py)
            g = -inverse_depth
            A = (
                g * d00, g * d01, g * (d00 * px + d01 * py),
                g * d01, g * d11, g * (d01 * px + d11 * py),
            )  # fmt: skip
            if jacobians[0] is not None:
                # dP/dω = -R [X]× Jr(ω), Jr = I - b K + e K²
                Jr = tuple((1.0 if i % 4 == 0 else 0.0) - b * K[i] + e * K2[i] for i in range(9))
                Xx = (0.0, -Z, Y, Z, 0.0, -X, -Y, X, 0.0)
                M = _mul(_mul(R, Xx), Jr)
                rows = []
                for r in range(2):
                    a0, a1, a2 = A[3 * r : 3 * r + 3]
                    rows += [-(a0 * M[j] + a1 * M[3 + j] + a2 * M[6 + j]) for j in range(3)]
                    rows += [a0, a1, a2]
                    p = px if r == 0 else py
                    rows += [radial * p, f * s * p, f * s * s * p]
                jacobians[0][:] = rows
            if jacobians[1] is not None:
                jacobians[1][:] = [
                    A[3 * r] * R[j] + A[3 * r + 1] * R[3 + j] + A[3 * r + 2] * R[6 + j]
                    for r in range(2)
                    for j in range(3)
                ]
            return True

    return SnavelyCost


def _mul(A, B):
    """The product of two row-major 3×3 matrices held as 9-tuples."""
    return tuple(
        A[3 * i] * B[j] + A[3 * i + 1] * B[3 + j] + A[3 * i + 2] * B[6 + j]
        for i in range(3)
        for j in range(3)
    )


def _solve_with_ceres(ceres_problem, iterations):
    """Ceres' LM with `SPARSE_SCHUR` (default threads) on a built `pyceres.Problem`; returns the
    wall time, Ceres' summary, its time spent evaluating residuals and Jacobians, and the steps
    tried (successful or not)."""
    import pyceres

    options = pyceres.SolverOptions()
    options.linear_solver_type = pyceres.LinearSolverType.SPARSE_SCHUR
    options.trust_region_strategy_type = pyceres.TrustRegionStrategyType.LEVENBERG_MARQUARDT
    options.max_num_iterations = iterations
    options.minimizer_progress_to_stdout = False
    summary = pyceres.SolverSummary()
    start = time.perf_counter()
    pyceres.solve(options, ceres_problem, summary)
    total = time.perf_counter() - start
    evaluation = summary.residual_evaluation_time_in_seconds
    evaluation += summary.jacobian_evaluation_time_in_seconds
    return total, summary, evaluation, summary.num_successful_steps + summary.num_unsuccessful_steps


def run_ceres(problem, iterations, loss, delta):
    import pyceres

    SnavelyCost = _snavely_cost_class()
    cameras, points = problem.cameras.copy(), problem.points.copy()
    ceres_problem = pyceres.Problem()
    loss_function = pyceres.HuberLoss(delta) if loss == "huber" else None
    for camera, point, observed in zip(
        problem.camera_indices.tolist(), problem.point_indices.tolist(), problem.observations
    ):
        ceres_problem.add_residual_block(
            SnavelyCost(observed.tolist()), loss_function, [cameras[camera], points[point]]
        )
    total, summary, evaluation, steps = _solve_with_ceres(ceres_problem, iterations)
    initial = cost(problem, problem.cameras, problem.points, loss, delta)
    final = cost(problem, cameras, points, loss, delta)
    checks = (("initial", initial, summary.initial_cost), ("final", final, summary.final_cost))
    for name, ours, theirs in checks:
        if not math.isclose(ours, theirs, rel_tol=1e-6):
            raise RuntimeError(f"Ceres' {name} cost {theirs} differs from the recomputed {ours}.")
    return Run(
        "Ceres (Python cost)",
        total,
        steps,
        initial,
        final,
        summary.final_cost,
        without_evaluation_s=total - evaluation,
        note=f"{summary.num_successful_steps} successful steps, "
        f"{summary.termination_type.name.lower()}, threads {summary.num_threads_used}",
    )


# --- Ceres with pycolmap's C++ cost ----------------------------------------------------------

_COLMAP_FLIP = np.diag([1.0, -1.0, -1.0])  # Rx(π): Snavely's camera looks down -z, COLMAP's +z


def _colmap_problem(problem, loss, delta):
    r"""`(reconstruction, bundle_adjuster, point ids)`: a `pycolmap.Reconstruction` of a BAL
    problem (camera $i$ is COLMAP camera, rig, frame and image $i + 1$, `RADIAL` with
    $(f, 0, 0, k_1, k_2)$, pose $(R_x(\pi)R, R_x(\pi)t)$, observations $(u_x, -u_y)$) and the
    Ceres problem COLMAP's default Ceres bundle adjuster builds on it (principal point constant,
    no gauge fixed; Huber as `ceres::HuberLoss(δ)`)."""
    import pycolmap
    from scipy.spatial.transform import Rotation

    reconstruction = pycolmap.Reconstruction()
    rotations = Rotation.from_rotvec(problem.cameras[:, :3]).as_matrix()
    order = np.argsort(problem.camera_indices, kind="stable")
    counts = np.bincount(problem.camera_indices, minlength=problem.num_cameras)
    starts = np.concatenate([[0], np.cumsum(counts)[:-1]])
    index_in_image = np.empty(problem.num_observations, dtype=np.int64)
    index_in_image[order] = np.arange(problem.num_observations) - np.repeat(starts, counts)
    flipped = problem.observations * np.array([1.0, -1.0])
    for i, (R, camera) in enumerate(zip(rotations, problem.cameras)):
        f, k1, k2 = camera[6:].tolist()
        reconstruction.add_camera_with_trivial_rig(
            pycolmap.Camera(
                model="RADIAL", width=1, height=1, params=[f, 0.0, 0.0, k1, k2], camera_id=i + 1
            )
        )
        keypoints = flipped[order[starts[i] : starts[i] + counts[i]]]
        image = pycolmap.Image(name=str(i), keypoints=keypoints, camera_id=i + 1, image_id=i + 1)
        pose = pycolmap.Rigid3d(pycolmap.Rotation3d(_COLMAP_FLIP @ R), _COLMAP_FLIP @ camera[3:6])
        reconstruction.add_image_with_trivial_frame(image, pose)
    tracks = [pycolmap.Track() for _ in range(problem.num_points)]
    for camera, point, k in zip(
        problem.camera_indices.tolist(), problem.point_indices.tolist(), index_in_image.tolist()
    ):
        tracks[point].add_element(camera + 1, k)
    point_ids = [
        reconstruction.add_point3D(xyz, track) for xyz, track in zip(problem.points, tracks)
    ]
    options = pycolmap.BundleAdjustmentOptions()
    options.refine_principal_point = False
    options.refine_focal_length = options.refine_extra_params = True
    if loss == "huber":
        options.ceres.loss_function_type = pycolmap.LossFunctionType.HUBER
        options.ceres.loss_function_scale = delta
    else:
        options.ceres.loss_function_type = pycolmap.LossFunctionType.TRIVIAL
    config = pycolmap.BundleAdjustmentConfig()
    for i in range(problem.num_cameras):
        config.add_image(i + 1)
    adjuster = pycolmap.create_default_ceres_bundle_adjuster(options, config, reconstruction)
    if adjuster.problem.num_residual_blocks() != problem.num_observations:
        raise RuntimeError(
            f"COLMAP's problem has {adjuster.problem.num_residual_blocks()} residual blocks "
            f"for {problem.num_observations} observations."
        )
    return reconstruction, adjuster, point_ids


def _colmap_initial_cost(ceres_problem, loss, delta):
    r"""$\tfrac12\sum\rho(\|r\|^2)$ from the residuals Ceres evaluates (2 per block, without
    the loss: Ceres returns corrected residuals where it applies it)."""
    import pyceres

    options = pyceres.EvaluateOptions()
    options.apply_loss_function = False
    r = np.asarray(ceres_problem.evaluate_residuals(options)).reshape(-1, 2)
    s = np.sum(r**2, axis=1)
    if loss == "huber":
        s = np.where(s <= delta**2, s, 2 * delta * np.sqrt(s) - delta**2)
    return 0.5 * float(np.sum(s))


def check_colmap_cost(problem, loss, delta, rel_tol=1e-9):
    """Raise unless Ceres' cost at the start with pycolmap's C++ cost equals `cost` to
    `rel_tol`; return both."""
    # the Ceres problem points into the reconstruction's memory: keep it alive while evaluating
    import pyceres

    reconstruction, adjuster, _ = _colmap_problem(problem, loss, delta)
    theirs = _colmap_initial_cost(adjuster.problem, loss, delta)
    # Ceres' own figure, with COLMAP's loss: a solve of no iterations only evaluates
    options = pyceres.SolverOptions()
    options.max_num_iterations = 0
    summary = pyceres.SolverSummary()
    pyceres.solve(options, adjuster.problem, summary)
    del adjuster, reconstruction
    ours = cost(problem, problem.cameras, problem.points, loss, delta)
    for name, value in (("residuals'", theirs), ("Ceres' own", summary.initial_cost)):
        if not math.isclose(ours, value, rel_tol=rel_tol):
            raise RuntimeError(
                f"pycolmap's initial cost ({name}) {value!r} differs from the NumPy {ours!r} "
                f"(relative {abs(value - ours) / ours:.3g} > {rel_tol:g})."
            )
    return ours, theirs, summary.initial_cost


def _from_colmap(problem, reconstruction, point_ids):
    """BAL cameras and points from the reconstruction (the inverse of `_colmap_problem`)."""
    from scipy.spatial.transform import Rotation

    cameras = np.empty_like(problem.cameras)
    for i in range(problem.num_cameras):
        pose = reconstruction.image(i + 1).cam_from_world()
        R = _COLMAP_FLIP @ pose.rotation.matrix()
        cameras[i, :3] = Rotation.from_matrix(R).as_rotvec()
        cameras[i, 3:6] = _COLMAP_FLIP @ pose.translation
        params = reconstruction.camera(i + 1).params
        if params[1] != 0 or params[2] != 0:
            raise RuntimeError(f"COLMAP moved camera {i}'s principal point to {params[1:3]}.")
        cameras[i, 6:] = params[0], params[3], params[4]
    points = np.stack([reconstruction.point3D(j).xyz for j in point_ids])
    return cameras, points


def run_ceres_colmap(problem, iterations, loss, delta):
    reconstruction, adjuster, point_ids = _colmap_problem(problem, loss, delta)
    ceres_problem = adjuster.problem
    initial = cost(problem, problem.cameras, problem.points, loss, delta)
    start_cost = _colmap_initial_cost(ceres_problem, loss, delta)
    if not math.isclose(initial, start_cost, rel_tol=1e-9):
        raise RuntimeError(f"pycolmap's initial cost {start_cost} differs from {initial}.")
    total, summary, evaluation, steps = _solve_with_ceres(ceres_problem, iterations)
    cameras, points = _from_colmap(problem, reconstruction, point_ids)
    final = cost(problem, cameras, points, loss, delta)
    if not math.isclose(initial, summary.initial_cost, rel_tol=1e-9):
        raise RuntimeError(f"Ceres' initial cost {summary.initial_cost} differs from {initial}.")
    behind = ""
    if not math.isclose(final, summary.final_cost, rel_tol=1e-9):
        # COLMAP's ReprojErrorCost returns a zero residual for a point behind its camera (as
        # GTSAM's GeneralSFMFactor), where Snavely's model projects it mirrored
        _, depth = ba.project_numpy(cameras[problem.camera_indices], points[problem.point_indices])
        zero = np.all(np.asarray(ceres_problem.evaluate_residuals()).reshape(-1, 2) == 0, axis=1)
        behind = (
            f", Ceres' own cost {summary.final_cost:.6g}: {int(np.sum(depth >= 0))} observations "
            f"behind their camera ({int(np.sum(zero))} zero residuals), which COLMAP's cost "
            "counts as zero error"
        )
    return Run(
        "Ceres (C++ cost via pycolmap), SPARSE_SCHUR, default threads",
        total,
        steps,
        initial,
        final,
        summary.final_cost,
        without_evaluation_s=total - evaluation,
        note=f"{summary.num_successful_steps} successful steps, "
        f"{summary.termination_type.name.lower()}, threads {summary.num_threads_used}, "
        f"evaluation {format_seconds(evaluation)}, "
        f"linear solver {format_seconds(summary.linear_solver_time_in_seconds)}, "
        f"{summary.num_effective_parameters} effective parameters" + behind,
    )


# --- GTSAM -------------------------------------------------------------------------------

_FLIP = np.diag([1.0, -1.0, -1.0])  # Rx(π): BAL's camera looks down -z, GTSAM's down +z


def _gtsam_values(problem):
    r"""GTSAM's cameras and points for a BAL problem: $^wR_c = R_{cw}^\top R_x(\pi)$,
    $^wt_c = -R_{cw}^\top t$ (GTSAM's `openGL2gtsam`), calibration
    `Cal3Bundler(f, k1, k2, 0, 0)`."""
    import gtsam
    from scipy.spatial.transform import Rotation

    rotations = Rotation.from_rotvec(problem.cameras[:, :3]).as_matrix()
    values = gtsam.Values()
    for i, (R, camera) in enumerate(zip(rotations, problem.cameras)):
        pose = gtsam.Pose3(gtsam.Rot3(R.T @ _FLIP), -R.T @ camera[3:6])
        calibration = gtsam.Cal3Bundler(camera[6], camera[7], camera[8], 0.0, 0.0)
        values.insert(gtsam.symbol("c", i), gtsam.PinholeCameraCal3Bundler(pose, calibration))
    for j, point in enumerate(problem.points):
        values.insert(gtsam.symbol("p", j), point)
    return values


def _from_gtsam(problem, values):
    """BAL cameras and points from GTSAM's values (the inverse of `_gtsam_values`)."""
    import gtsam
    from scipy.spatial.transform import Rotation

    cameras = np.empty_like(problem.cameras)
    for i in range(problem.num_cameras):
        camera = values.atPinholeCameraCal3Bundler(gtsam.symbol("c", i))
        pose, calibration = camera.pose(), camera.calibration()
        R = _FLIP @ pose.rotation().matrix().T
        cameras[i, :3] = Rotation.from_matrix(R).as_rotvec()
        cameras[i, 3:6] = -R @ pose.translation()
        cameras[i, 6:] = calibration.fx(), calibration.k1(), calibration.k2()
    points = np.stack([values.atPoint3(gtsam.symbol("p", j)) for j in range(problem.num_points)])
    return cameras, points


def run_gtsam(problem, iterations, loss, delta, schur=False):
    import gtsam

    noise = gtsam.noiseModel.Unit.Create(2)
    if loss == "huber":
        huber = gtsam.noiseModel.mEstimator.Huber.Create(delta)
        noise = gtsam.noiseModel.Robust.Create(huber, noise)
    graph = gtsam.NonlinearFactorGraph()
    flipped = problem.observations * np.array([1.0, -1.0])  # GTSAM's image y points down
    for camera, point, observed in zip(
        problem.camera_indices.tolist(), problem.point_indices.tolist(), flipped
    ):
        graph.add(
            gtsam.GeneralSFMFactorCal3Bundler(
                observed, noise, gtsam.symbol("c", camera), gtsam.symbol("p", point)
            )
        )
    initial = _gtsam_values(problem)
    if schur:
        # the plain defaults raise an empty RuntimeError on these problems (both elimination
        # modes); GTSAM's Ceres-style defaults (diagonal damping, λ₀ = 1e-4, factor 2) solve
        params = gtsam.SfmLevenbergMarquardtParams.ceresDefaults()
        params.setEliminationMode(gtsam.SfmEliminationMode.Schur)
    else:
        params = gtsam.LevenbergMarquardtParams()
    params.setMaxIterations(iterations)
    start = time.perf_counter()
    if schur:
        optimizer = gtsam.SfmLevenbergMarquardtOptimizer(graph, initial, params)
    else:
        optimizer = gtsam.LevenbergMarquardtOptimizer(graph, initial, params)
    result = optimizer.optimize()
    total = time.perf_counter() - start
    cameras, points = _from_gtsam(problem, result)
    initial_cost = cost(problem, problem.cameras, problem.points, loss, delta)
    final_cost = cost(problem, cameras, points, loss, delta)
    note = ""
    if not math.isclose(final_cost, graph.error(result), rel_tol=1e-6):
        # GeneralSFMFactor returns a zero error for a point behind its camera (it catches
        # GTSAM's CheiralityException), where Snavely's model projects it mirrored
        _, depth = ba.project_numpy(cameras[problem.camera_indices], points[problem.point_indices])
        note = (
            f"GTSAM's own cost {graph.error(result):.6g}: {int(np.sum(depth >= 0))} observations "
            "behind their camera, which GeneralSFMFactor counts as zero error"
        )
    name = "GTSAM Sfm LM, Schur" if schur else "GTSAM LM"
    own = graph.error(result)
    return Run(name, total, optimizer.iterations(), initial_cost, final_cost, own, note=note)


# --- lieax -------------------------------------------------------------------------------


def run_lieax(problem, iterations, loss, delta, damping="identity", lambda_update="gtsam"):
    r"""`lieax.factorgraph` (the general sparse solver) with `lieax.ba.camera_residual` and its
    closed-form `camera_jacobians`: cameras one `(SE3, intrinsics)` variable kind, points
    another, eliminated by the Schur complement, LM with `damping` (`"marquardt"`:
    $\lambda\,\mathrm{diag}(H)$, as Ceres and GTSAM's `ceresDefaults`; `"identity"`:
    $\lambda I$), the $\lambda$ rule `lambda_update` (`LevenbergMarquardt`'s `damping_update`: `"nielsen"`: Ceres', from Ceres' initial
    $\lambda = 10^{-4}$; `"gtsam"`: GTSAM's, from $10^{-5}$) and the iteration cap, no gauge prior (`check_gauge=False`: the damping handles
    it, as for the others). `total` is a warm solve; the first one (structure analysis and XLA
    compilation) is in the note."""
    from lieax import lstsq

    solve = lieax_solver(problem, iterations, loss, delta, damping, lambda_update)
    start = time.perf_counter()
    solve()
    first = time.perf_counter() - start
    start = time.perf_counter()
    result = solve()
    total = time.perf_counter() - start
    (pose, intrinsics), solved = result.values
    cameras_bal = np.asarray(ba.camera_to_bal(pose, intrinsics))
    final = cost(problem, cameras_bal, np.asarray(solved), loss, delta)
    initial = cost(problem, problem.cameras, problem.points, loss, delta)
    return Run(
        "lieax.factorgraph, Schur"
        + (", diag damping" if damping == "marquardt" else "")
        + (", Ceres' λ rule" if lambda_update == "nielsen" else ""),
        total,
        int(result.iterations),
        initial,
        final,
        float(result.cost),
        note=f"first call {format_seconds(first)}, {int(result.linear_solves)} linear solves, "
        f"{lstsq.Status(int(result.status)).name}",
    )


def lieax_solver(problem, iterations, loss, delta, damping="marquardt", lambda_update="nielsen"):
    """`solve()`: `run_lieax`'s solve from the problem's start (its result, waited for)."""
    import jax.numpy as jnp

    from lieax import factorgraph as fg
    from lieax import lstsq

    pose, intrinsics = problem.camera_variables(jnp.float64)
    cameras = fg.Var((pose, intrinsics), name="cameras")
    points = fg.Var(jnp.asarray(problem.points), name="points")
    reprojection = fg.Factor(
        ba.camera_residual,
        (cameras[problem.camera_indices], points[problem.point_indices]),
        jnp.asarray(problem.observations),
        loss=lstsq.Huber(delta) if loss == "huber" else None,
        jacobian_fn=ba.camera_jacobians,
        name="reprojection",
    )
    graph = fg.FactorGraph([reprojection], check_gauge=False)

    def solve():
        result = graph.solve(
            eliminate=points,
            solver=lstsq.LevenbergMarquardt.gtsam(
                scaling="clipped" if damping == "marquardt" else "identity",
                damping_update=lambda_update,
                initial_damping=1e-4 if lambda_update == "nielsen" else 1e-5,
            ),
            # with Ceres' rule, Ceres' stopping test too: function_tolerance 1e-6 (relative)
            termination=lstsq.Termination.gtsam(
                max_iterations=iterations,
                function_tolerance=1e-6 if lambda_update == "nielsen" else 1e-5,
            ),
            throw=False,
        )
        return jax.block_until_ready(result)

    return solve


def _seconds_or_blank(seconds):
    return "" if math.isnan(seconds) else format_seconds(seconds)


SOLVERS = {
    "ceres": run_ceres,
    "ceres-colmap": run_ceres_colmap,
    "gtsam": run_gtsam,
    "gtsam-schur": lambda *args: run_gtsam(*args, schur=True),
    "lieax": run_lieax,
    "lieax-gtsam-rule": lambda *args: run_lieax(*args, damping="marquardt", lambda_update="gtsam"),
}


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--problem", default="ladybug-49")
    parser.add_argument("--iterations", type=int, default=20)
    parser.add_argument("--loss", choices=("trivial", "huber"), default="trivial")
    parser.add_argument("--huber-delta", type=float, default=2.0)
    parser.add_argument("--outliers", type=float, default=0.0, help="synthetic problems only")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--rounds", type=int, default=1, help="interleaved runs per solver")
    parser.add_argument("--solvers", default="ceres,ceres-colmap,gtsam,gtsam-schur,lieax")
    parser.add_argument("--lieax-damping", choices=("identity", "marquardt"), default="marquardt")
    parser.add_argument("--lieax-lambda-update", choices=("nielsen", "gtsam"), default="nielsen")
    args = parser.parse_args(argv)
    solvers = args.solvers.split(",")
    unknown = [s for s in solvers if s not in SOLVERS]
    if unknown:
        parser.error(f"unknown solvers {unknown}; choose from {list(SOLVERS)}.")

    name, problem = load_problem(args.problem, outliers=args.outliers, seed=args.seed)
    print(machine_description())
    print(
        f"{name}: {problem.num_cameras} cameras, {problem.num_points} points, "
        f"{problem.num_observations} observations; loss {args.loss}"
        + (f" (δ = {args.huber_delta} px)" if args.loss == "huber" else "")
        + f", at most {args.iterations} iterations\n"
    )
    if "ceres-colmap" in solvers:  # before anything is timed
        try:
            import pycolmap
        except ImportError:
            print("ceres-colmap: not available (pip install pycolmap)\n")
            solvers.remove("ceres-colmap")
    if "ceres-colmap" in solvers:
        ours, theirs, own = check_colmap_cost(problem, args.loss, args.huber_delta)
        print(
            f"pycolmap {pycolmap.__version__} (Ceres {pycolmap.__ceres_version__}): initial "
            f"cost {theirs!r} from its C++ cost's residuals, {own!r} by Ceres, {ours!r} by "
            f"NumPy (relative differences {abs(theirs - ours) / ours:.2g}, "
            f"{abs(own - ours) / ours:.2g})\n",
            flush=True,
        )
    # rounds: every solver once per round, in an order rotated from round to round (machine
    # noise falls on all alike); each row is the median round
    samples, failures = {}, []
    for r in range(args.rounds):
        shift = r % len(solvers)
        for solver in solvers[shift:] + solvers[:shift]:
            if any(f.startswith(f"{solver}:") for f in failures):
                continue
            try:
                options = (
                    {"damping": args.lieax_damping, "lambda_update": args.lieax_lambda_update}
                    if solver == "lieax"
                    else {}
                )
                run = SOLVERS[solver](
                    problem, args.iterations, args.loss, args.huber_delta, **options
                )
            except RuntimeError as error:  # GTSAM raises with an empty message where it fails
                failures.append(
                    f"{solver}: failed ({type(error).__name__}: {error or 'no message'})"
                )
                print(failures[-1], flush=True)
                continue
            if run is not None:
                samples.setdefault(solver, []).append(run)
                print(f"{run.solver}: {format_seconds(run.total_s)} {run.note}", flush=True)
    runs = [
        dataclasses.replace(
            samples[s][0],
            total_s=statistics.median(run.total_s for run in samples[s]),
            without_evaluation_s=statistics.median(run.without_evaluation_s for run in samples[s]),
        )
        for s in solvers
        if s in samples
    ]
    headers = [
        "solver", "total", "iterations", "per iteration", "Ceres w/o eval.", "initial cost",
        "final cost", "solver's own final cost",
    ]  # fmt: skip
    rows = [
        [
            run.solver,
            format_seconds(run.total_s),
            run.iterations,
            format_seconds(run.total_s / max(run.iterations, 1)),
            _seconds_or_blank(run.without_evaluation_s),
            f"{run.initial_cost:.6g}",
            f"{run.final_cost:.8g}",
            f"{run.own_final_cost:.8g}",
        ]
        for run in runs
    ]
    print()
    print(markdown_table(headers, rows))
    for line in [f"{run.solver}: {run.note}" for run in runs if run.note] + failures:
        print(f"\n{line}")


if __name__ == "__main__":
    main()
