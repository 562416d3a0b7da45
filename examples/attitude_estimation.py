r"""Attitude of a diving elephant seal from accelerometer and magnetometer readings, the
application of Sommer, Pradalier and Furgale, "Automatic Differentiation on Differentiable
Manifolds as a Tool for Robotics" (Sec. 4.2).

State at every sample $t$: the attitude $C_t \in SO(3)$ (`C_world_body`, body x along the animal)
and the propulsion $P_t$ it applies along its body x axis. With $G = (0, 0, 9.81)$ and the
magnetic field $B$ constant in the world frame (x north, y west, z up), the accelerometer reads
$a_t = C_t^\top G + P_t\,x$ and the magnetometer $b_t = C_t^\top B$, both noisy. The residuals
(whitened by their standard deviations) are the paper's

- accelerometer $C_t (a_t - P_t x) - G$ and magnetometer $C_t b_t - B$,
- smoothness $P_t - P_{t-1}$ and $\mathrm{Log}(C_{t-1}^{-1} C_t)$,

minimized over every $C_t$ (right perturbation $C_t \oplus \delta_t$) and $P_t$ by
`lieax.lstsq.least_squares` (Levenberg-Marquardt), whose Jacobian blocks come from lieax's
closed-form rules. As in the paper the solve starts at zero propulsion and the attitude each
sample gives on its own (TRIAD: gravity from the accelerometer, heading from the magnetometer),
which the propulsion tilts by a few degrees.

The data are generated with a known ground truth: repeated dives (gliding nose-down descent,
bottom phase with flipper strokes and rolls, stroking ascent) sampled at 1 Hz, accelerometer
noise 0.05 m/s² (sensor noise and unmodelled body accelerations), magnetometer noise 0.2 µT, a
field of 47 µT with an inclination of -65° (roughly the Kerguelen Islands', where the paper's
data were recorded). `least_squares` solves dense normal equations, so a long record is solved
in overlapping windows of the same length (compiled once); each sample keeps the estimate of the
window whose centre is nearest.

    python examples/attitude_estimation.py [--samples 1200] [--window 150] [--overlap 15] [--verbose]
"""

import argparse
import math
import time

import jax
import jax.numpy as jnp
import numpy as np

import lieax
from lieax import lstsq

GRAVITY = np.array([0.0, 0.0, 9.81])  # what an accelerometer at rest reads, in the world frame
INCLINATION = np.deg2rad(-65.0)  # southern hemisphere: the field points up, out of the ground
FIELD = 47.0 * np.array([np.cos(INCLINATION), 0.0, -np.sin(INCLINATION)])  # µT, world x north, z up
SIGMA_ACC = 0.05  # m/s²
SIGMA_MAG = 0.2  # µT
SIGMA_PROPULSION_STEP = 0.25  # m/s² per sample, smoothness of P
SIGMA_ROTATION_STEP = 0.05  # rad per sample, smoothness of C


# ---- synthetic dives ------------------------------------------------------------------------------


def _smooth(rng, n, sigma, width):
    """A smooth random signal: white noise convolved with a Gaussian window of `width` samples."""
    kernel = np.exp(-0.5 * (np.arange(-3 * width, 3 * width + 1) / width) ** 2)
    noise = rng.normal(size=n + kernel.size - 1)
    signal = np.convolve(noise, kernel / np.sqrt(np.sum(kernel**2)), mode="valid")
    return sigma * signal


def _smoothstep(x):
    """0 below 0, 1 above 1, a smooth cubic between."""
    x = np.clip(x, 0.0, 1.0)
    return x * x * (3.0 - 2.0 * x)


def simulate(samples, *, dive_period=480.0, seed=0):
    """A record of `samples` seconds at 1 Hz: ground truth and sensor readings.

    **Returns:** a dict with `rpy` `(T, 3)` (roll, pitch, yaw, rad; `SO3.from_rpy` order),
    `propulsion` `(T,)` (m/s²), `acc` `(T, 3)` (m/s²) and `mag` `(T, 3)` (µT) in the body frame.
    """
    rng = np.random.default_rng(seed)
    t = np.arange(samples, dtype=float)
    phase = (t % dive_period) / dive_period  # 0: leaving the surface, 1: back at it
    up = lambda start, width: _smoothstep((phase - start) / width)
    descent = up(0.0, 0.05) * (1.0 - up(0.30, 0.08))
    bottom = up(0.30, 0.08) * (1.0 - up(0.62, 0.08))
    ascent = up(0.62, 0.08) * (1.0 - up(0.92, 0.05))
    # positive pitch about body y (left) puts the nose down
    pitch = np.deg2rad(55.0) * descent - np.deg2rad(50.0) * ascent
    pitch += bottom * np.deg2rad(12.0) * np.sin(2 * np.pi * t / 37.0) + _smooth(
        rng, samples, 0.05, 8
    )
    roll = np.deg2rad(10.0) * np.sin(2 * np.pi * t / 23.0 + 1.0) + _smooth(rng, samples, 0.2, 15)
    yaw = np.cumsum(_smooth(rng, samples, 0.04, 10)) + rng.uniform(-np.pi, np.pi)
    strokes = 0.4 + 0.35 * np.sin(2 * np.pi * t / 6.5)  # flipper strokes, m/s² along body x
    propulsion = (1.0 - 0.9 * descent) * strokes + _smooth(rng, samples, 0.05, 5)

    rotation = np.asarray(lieax.SO3.from_rpy(roll, pitch, yaw).as_matrix())  # C_world_body
    x_axis = np.array([1.0, 0.0, 0.0])
    acc = np.einsum("tji,j->ti", rotation, GRAVITY) + propulsion[:, None] * x_axis
    mag = np.einsum("tji,j->ti", rotation, FIELD)
    acc += SIGMA_ACC * rng.normal(size=acc.shape)
    mag += SIGMA_MAG * rng.normal(size=mag.shape)
    return {
        "rpy": np.stack([roll, pitch, yaw], 1),
        "propulsion": propulsion,
        "acc": acc,
        "mag": mag,
    }


def triad(acc, mag):
    """Attitude from one accelerometer and one magnetometer reading each (Black's TRIAD): the
    accelerometer taken as pure gravity gives the world's up axis in the body frame, the
    magnetometer then its north axis. Rows of `C_world_body` are the world axes in body
    coordinates."""
    up = acc / np.linalg.norm(acc, axis=-1, keepdims=True)
    west = np.cross(up, mag)  # up × B points west (B has no west component)
    west /= np.linalg.norm(west, axis=-1, keepdims=True)
    north = np.cross(west, up)
    return lieax.SO3.from_matrix(jnp.asarray(np.stack([north, west, up], axis=-2)))


# ---- the least-squares problem ------------------------------------------------------------------


def residuals(state, data):
    """The whitened residuals of one window: `state = (C (T,), P (T,))`,
    `data = (acc (T, 3), mag (T, 3))`."""
    C, P = state
    acc, mag = data
    x_axis = jnp.array([1.0, 0.0, 0.0], dtype=acc.dtype)
    accelerometer = (C @ (acc - P[:, None] * x_axis) - GRAVITY) / SIGMA_ACC
    magnetometer = (C @ mag - FIELD) / SIGMA_MAG
    propulsion_step = (P[1:] - P[:-1]) / SIGMA_PROPULSION_STEP
    rotation_step = C[1:].rminus(C[:-1]) / SIGMA_ROTATION_STEP  # Log(C_{t-1}^{-1} C_t)
    return accelerometer, magnetometer, propulsion_step, rotation_step


def window_starts(samples, window, overlap):
    """Starts of windows of `window` samples, consecutive windows sharing `2 * overlap` samples,
    the last one ending at the last sample."""
    if samples <= window:
        return np.array([0])
    step = window - 2 * overlap
    count = math.ceil((samples - window) / step) + 1
    return np.minimum(np.arange(count) * step, samples - window)


def stitch(estimates, starts, samples, window):
    """For each sample, the estimate of the window whose centre is nearest (`estimates` `(K, W, ...)`)."""
    t = np.arange(samples)
    centres = starts + 0.5 * (window - 1)
    k = np.argmin(np.abs(t[:, None] - centres[None, :]), axis=1)
    return estimates[k, t - starts[k]]


def solve(record, window, overlap, *, verbose=False, max_iterations=50):
    """Estimate `(C (T,), P (T,), solutions)` for a record, one least-squares solve per window
    (`solutions` stacks the windows' `Solution`s)."""
    samples = record["acc"].shape[0]
    window = min(window, samples)
    starts = window_starts(samples, window, overlap)
    solutions = []
    for start in starts:  # every window has the same shapes: compiled once, then reused
        acc = record["acc"][start : start + window]
        mag = record["mag"][start : start + window]
        x0 = (triad(acc, mag), jnp.zeros(window))  # the paper's start: TRIAD, no propulsion
        solutions.append(
            lstsq.least_squares(
                residuals,
                x0,
                (jnp.asarray(acc), jnp.asarray(mag)),
                termination=lstsq.Termination(max_iterations=max_iterations),
                verbose=verbose,
            )
        )
    solutions = jax.tree_util.tree_map(lambda *leaves: jnp.stack(leaves), *solutions)
    C = stitch(np.asarray(solutions.value[0].parameters()), starts, samples, window)
    P = stitch(np.asarray(solutions.value[1]), starts, samples, window)
    return lieax.SO3(jnp.asarray(C)), jnp.asarray(P), solutions


def angle_errors_deg(C_est, C_true):
    r"""Geodesic angle $|\mathrm{Log}(C_{true}^{-1} C_{est})|$ per sample, degrees."""
    return np.rad2deg(np.linalg.norm(np.asarray(C_est.rminus(C_true)), axis=-1))


def tilt_and_heading_errors_deg(C_est, C_true):
    """Tilt error (angle between the estimated and true up axes in the body frame) and heading
    error (yaw difference, wrapped), degrees, per sample."""
    up = np.array([0.0, 0.0, 1.0])
    up_est = np.asarray(C_est.inverse() @ up)
    up_true = np.asarray(C_true.inverse() @ up)
    tilt = np.degrees(np.arccos(np.clip(np.sum(up_est * up_true, -1), -1.0, 1.0)))
    yaw = np.asarray(C_est.as_rpy())[:, 2] - np.asarray(C_true.as_rpy())[:, 2]
    heading = np.degrees(np.abs(np.angle(np.exp(1j * yaw))))
    return tilt, heading


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--samples", type=int, default=600, help="seconds of record at 1 Hz")
    parser.add_argument("--window", type=int, default=100, help="samples per least-squares window")
    parser.add_argument("--overlap", type=int, default=10, help="samples shared at each window end")
    parser.add_argument("--max-iterations", type=int, default=50)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--verbose", action="store_true", help="print the solver's iteration table")
    args = parser.parse_args(argv)
    if args.window <= 2 * args.overlap:
        parser.error("--window must be larger than twice --overlap")
    jax.config.update("jax_enable_x64", True)

    record = simulate(args.samples, seed=args.seed)
    C_true = lieax.SO3.from_rpy(*jnp.asarray(record["rpy"]).T)
    C_triad = triad(record["acc"], record["mag"])

    start = time.perf_counter()
    C, P, solutions = solve(
        record, args.window, args.overlap, verbose=args.verbose, max_iterations=args.max_iterations
    )
    jax.block_until_ready(C.parameters())
    first = time.perf_counter() - start
    start = time.perf_counter()
    jax.block_until_ready(
        solve(record, args.window, args.overlap, max_iterations=args.max_iterations)[0].parameters()
    )
    second = time.perf_counter() - start

    windows = int(solutions.iterations.shape[0])
    statuses = dict(
        zip(*np.unique(np.asarray(solutions.status_name, dtype=str), return_counts=True))
    )
    print(
        f"{args.samples} samples at 1 Hz, {windows} window(s) of {min(args.window, args.samples)} "
        f"samples, {4 * min(args.window, args.samples)} unknowns each"
    )
    print(
        f"solver: {', '.join(f'{n} {s}' for s, n in statuses.items())}; iterations "
        f"{int(np.min(solutions.iterations))}-{int(np.max(solutions.iterations))}; cost "
        f"{float(np.sum(solutions.cost_history[:, 0])):.4g} -> {float(np.sum(solutions.cost)):.4g}"
    )
    print(f"time: {first:.2f} s first call (with compilation), {second:.3f} s second call")

    summary = {}
    print(
        f"{'attitude error (deg)':<24}{'mean':>8}{'rms':>8}{'max':>8}{'tilt rms':>10}{'heading rms':>13}"
    )
    for name, estimate in (("TRIAD, per sample", C_triad), ("least squares", C)):
        error = angle_errors_deg(estimate, C_true)
        tilt, heading = tilt_and_heading_errors_deg(estimate, C_true)
        rms = lambda e: float(np.sqrt(np.mean(e**2)))
        print(
            f"{name:<24}{error.mean():>8.3f}{rms(error):>8.3f}{error.max():>8.3f}"
            f"{rms(tilt):>10.3f}{rms(heading):>13.3f}"
        )
        summary[name] = rms(error)
    propulsion_rms = float(np.sqrt(np.mean((np.asarray(P) - record["propulsion"]) ** 2)))
    print(
        f"propulsion: rms error {propulsion_rms:.3f} m/s² (true values "
        f"{record['propulsion'].min():.2f} to {record['propulsion'].max():.2f} m/s²)"
    )
    return {
        "triad_rms_deg": summary["TRIAD, per sample"],
        "rms_deg": summary["least squares"],
        "propulsion_rms": propulsion_rms,
        "converged": bool(np.all(np.asarray(solutions.converged))),
    }


if __name__ == "__main__":
    main()
