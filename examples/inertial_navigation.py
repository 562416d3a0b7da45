"""Estimate a vehicle's poses, velocities and IMU biases from a 200 Hz IMU and 1 Hz position
fixes with `lieax.imu` factors solved by `lieax.factorgraph` (a GNSS/INS smoother).

The vehicle drives with turns and accelerations; its IMU (noise densities and bias random walks
of a MEMS unit like EuRoC's ADIS16448) carries constant-plus-random-walk biases; the position
fixes have 0.5 m noise. Keyframes are the fixes; the samples between two are preintegrated
(`preintegrate_intervals`), giving one IMU factor and one bias random-walk factor per interval. The
start is what a filter would have: positions from the fixes, headings and velocities from their
differences, zero biases.

    python examples/inertial_navigation.py [--keyframes 300] [--plot ins.png] [--combined]

`--combined` joins each interval's two factors in one `combined_imu_factor` (GTSAM's
`CombinedImuFactor`), whitened by `preintegrate_combined`'s 15×15 covariance.
"""

import argparse
import time

import jax
import jax.numpy as jnp
import numpy as np

RATE = 200  # IMU samples per second (and per keyframe interval: fixes at 1 Hz)
GRAVITY = 9.81
ACCEL_DENSITY, GYRO_DENSITY = 2.0e-3, 1.7e-4  # m/s²/√Hz, rad/s/√Hz
ACCEL_BIAS_WALK, GYRO_BIAS_WALK = 3.0e-3, 1.9e-5  # m/s³/√Hz, rad/s²/√Hz
FIX_SIGMA = 0.5  # m


def simulate(keyframes, rng, rate=RATE):
    r"""A drive of `keyframes - 1` seconds: returns a dict with the true keyframe states
    (`rotations` (n, 3, 3), `positions`, `velocities` (n, 3), `biases` (n, 6)), the IMU samples
    per interval (`gyro`, `accel` (n - 1, rate, 3)), `dt` and the position `fixes` (n, 3).

    The truth is integrated with piecewise constant body rates and accelerations, the model the
    preintegration assumes: $R^+ = R\,\mathrm{Exp}(\omega\delta t)$, $v^+ = v + a\delta t$,
    $p^+ = p + v\delta t + \tfrac12 a \delta t^2$."""
    dt = 1.0 / rate
    steps = (keyframes - 1) * rate
    t = np.arange(steps) * dt
    yaw_rate = 0.25 * np.sin(2 * np.pi * t / 40.0) + 0.1 * np.sin(2 * np.pi * t / 13.0)
    roll_rate = 0.05 * np.sin(2 * np.pi * t / 7.0)
    pitch_rate = 0.03 * np.cos(2 * np.pi * t / 11.0)
    forward = 0.6 * np.sin(2 * np.pi * t / 25.0)  # m/s², speeding up and braking
    g = np.array([0.0, 0.0, -GRAVITY])
    rotation, position, velocity = np.eye(3), np.zeros(3), np.array([8.0, 0.0, 0.0])
    bias = np.concatenate([rng.normal(0, 0.05, 3), rng.normal(0, 0.003, 3)])
    walk = np.repeat([ACCEL_BIAS_WALK, GYRO_BIAS_WALK], 3) * np.sqrt(dt)
    states, biases, gyro, accel = [], [], np.zeros((steps, 3)), np.zeros((steps, 3))
    for k in range(steps):
        if k % rate == 0:
            states.append((rotation, position, velocity))
            biases.append(bias)
        omega = np.array([roll_rate[k], pitch_rate[k], yaw_rate[k]])
        speed_body = rotation.T @ velocity
        a_body = np.array([forward[k], speed_body[0] * yaw_rate[k], 0.0])  # along the road
        a_nav = rotation @ a_body
        gyro[k] = omega + bias[3:] + rng.normal(0, GYRO_DENSITY / np.sqrt(dt), 3)
        accel[k] = (
            rotation.T @ (a_nav - g) + bias[:3] + rng.normal(0, ACCEL_DENSITY / np.sqrt(dt), 3)
        )
        position = position + velocity * dt + 0.5 * a_nav * dt * dt
        velocity = velocity + a_nav * dt
        rotation = rotation @ _exp(omega * dt)
        bias = bias + rng.normal(0, 1, 6) * walk
    states.append((rotation, position, velocity))
    biases.append(bias)
    positions = np.array([s[1] for s in states])
    return {
        "rotations": np.array([s[0] for s in states]),
        "positions": positions,
        "velocities": np.array([s[2] for s in states]),
        "biases": np.array(biases),
        "gyro": gyro.reshape(keyframes - 1, rate, 3),
        "accel": accel.reshape(keyframes - 1, rate, 3),
        "dt": dt,
        "fixes": positions + rng.normal(0, FIX_SIGMA, positions.shape),
    }


def _exp(omega):
    r"""Rodrigues' $\mathrm{Exp}(\omega)$ (NumPy, for the simulation)."""
    theta = np.linalg.norm(omega)
    k = np.array([[0, -omega[2], omega[1]], [omega[2], 0, -omega[0]], [-omega[1], omega[0], 0]])
    if theta < 1e-12:
        return np.eye(3) + k
    return np.eye(3) + np.sin(theta) / theta * k + (1 - np.cos(theta)) / theta**2 * (k @ k)


def params():
    import lieax.imu

    return lieax.imu.ImuParams.make_u(
        GRAVITY,
        accel_noise_density=ACCEL_DENSITY,
        gyro_noise_density=GYRO_DENSITY,
        integration_sigma=1e-4,
    )


def initial_guess(fixes):
    """Positions from the fixes, yaw and velocity from their central differences (level
    attitude), zero biases: `(rotations (n, 3, 3), positions, velocities, biases)`."""
    velocities = np.gradient(fixes, axis=0)  # fixes 1 s apart
    yaw = np.arctan2(velocities[:, 1], velocities[:, 0])
    c, s, zero, one = np.cos(yaw), np.sin(yaw), np.zeros_like(yaw), np.ones_like(yaw)
    rotations = np.stack(
        [np.stack([c, -s, zero], -1), np.stack([s, c, zero], -1), np.stack([zero, zero, one], -1)],
        axis=1,
    )
    return rotations, fixes, velocities, np.zeros((len(fixes), 6))


def build_graph(data, pim, imu_params, covariance=None):
    """The factor graph: IMU and bias random-walk factors per interval (with `covariance`,
    `preintegrate_combined`'s, one combined IMU factor instead), a position prior per
    keyframe, a weak prior on the first velocity and bias. Returns `(graph, (poses, velocities,
    biases))`."""
    import lieax.imu
    from lieax.factorgraph import Factor, FactorGraph, Var

    n = len(data["fixes"])
    rotations, positions, velocities, biases = initial_guess(data["fixes"])
    # constructors on NumPy input, NumPy values and data: building compiles nothing
    pose_values = lieax.SE3.from_rotation_and_translation(
        lieax.SO3.from_matrix(rotations), positions
    )
    poses = Var(pose_values, name="poses")
    vels = Var(velocities, name="velocities")
    bias = Var(biases, name="biases")
    i, j, every = np.arange(n - 1), np.arange(1, n), np.arange(n)
    first = np.array([0])
    if covariance is None:
        inertial = [
            lieax.imu.imu_factor(pim, imu_params, poses[i], vels[i], poses[j], vels[j], bias[i]),
            lieax.imu.bias_random_walk_factor(
                bias[i], bias[j], np.asarray(pim.delta_t), ACCEL_BIAS_WALK, GYRO_BIAS_WALK
            ),
        ]
    else:
        inertial = [
            lieax.imu.combined_imu_factor(
                pim, covariance, imu_params, poses[i], vels[i], poses[j], vels[j], bias[i], bias[j]
            )
        ]
    factors = [
        *inertial,
        Factor(
            lambda x, z: x.translation() - z,
            (poses[every],),
            data["fixes"],
            sqrt_information=np.eye(3) / FIX_SIGMA,
            name="position_fix",
        ),
        Factor(
            lambda v, z: v - z,
            (vels[first],),
            velocities[:1],
            sqrt_information=np.eye(3) / 1.0,
            name="velocity_prior",
        ),
        Factor(
            lambda b: b,
            (bias[first],),
            sqrt_information=np.diag(np.repeat([1 / 0.1, 1 / 0.01], 3)),
            name="bias_prior",
        ),
    ]
    return FactorGraph(factors), (poses, vels, bias)


def preintegrate_all(data, imu_params, combined=False):
    """`preintegrate_intervals` over the intervals (one compiled call; intervals of different
    sample counts would be padded with masks), at zero bias (the initial guess); `combined`:
    with the bias random walk, as `preintegrate_combined`, `(pim, covariance)`."""
    import lieax.imu

    walk = lieax.imu.BiasRandomWalk.isotropic(ACCEL_BIAS_WALK, GYRO_BIAS_WALK)
    return lieax.imu.preintegrate_intervals(
        imu_params,
        accel=data["accel"],
        gyro=data["gyro"],
        dt=data["dt"],
        walk=walk if combined else None,
    )


def errors(data, values):
    """RMS position (m), velocity (m/s), attitude (deg) and bias errors against the truth."""
    poses, velocities, biases = values
    rotation_error = jax.vmap(lambda r, q: (r.inverse() @ q).log())(
        poses.rotation(),
        jax.vmap(__import__("lieax").SO3.from_matrix)(jnp.asarray(data["rotations"])),
    )
    rms = lambda x: float(np.sqrt(np.mean(np.sum(np.square(x), axis=-1))))  # noqa: E731
    return {
        "position_rms": rms(np.asarray(poses.translation()) - data["positions"]),
        "velocity_rms": rms(np.asarray(velocities) - data["velocities"]),
        "attitude_rms_deg": np.rad2deg(rms(np.asarray(rotation_error))),
        "accel_bias_rms": rms(np.asarray(biases)[:, :3] - data["biases"][:, :3]),
        "gyro_bias_rms": rms(np.asarray(biases)[:, 3:] - data["biases"][:, 3:]),
        "fix_rms": rms(data["fixes"] - data["positions"]),
    }


def plot(path, data, values):
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    poses, velocities, biases = values
    estimated, truth = np.asarray(poses.translation()), data["positions"]
    t = np.arange(len(truth))
    figure, axes = plt.subplots(1, 3, figsize=(15, 4.5))
    axes[0].plot(truth[:, 0], truth[:, 1], "k-", label="truth")
    axes[0].plot(data["fixes"][:, 0], data["fixes"][:, 1], ".", ms=2, color="0.6", label="fixes")
    axes[0].plot(estimated[:, 0], estimated[:, 1], "C0-", lw=1, label="estimate")
    axes[0].set_aspect("equal")
    axes[0].set_title("trajectory (m)")
    axes[0].legend()
    axes[1].plot(t, np.linalg.norm(estimated - truth, axis=1), label="position (m)")
    axes[1].plot(
        t,
        np.linalg.norm(np.asarray(velocities) - data["velocities"], axis=1),
        label="velocity (m/s)",
    )
    axes[1].set_title("errors")
    axes[1].set_xlabel("time (s)")
    axes[1].legend()
    for k, name in enumerate(["$b_{a,x}$", "$b_{a,y}$", "$b_{a,z}$"]):
        axes[2].plot(t, np.asarray(biases)[:, k], f"C{k}-", label=name)
        axes[2].plot(t, data["biases"][:, k], f"C{k}--")
    axes[2].set_title("accelerometer biases (m/s², dashed: truth)")
    axes[2].legend()
    figure.tight_layout()
    figure.savefig(path, dpi=100)
    plt.close(figure)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--keyframes", type=int, default=300)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--plot", help="save a figure of the trajectory, errors and biases")
    parser.add_argument(
        "--combined", action="store_true", help="one combined IMU factor per interval"
    )
    args = parser.parse_args(argv)
    jax.config.update("jax_enable_x64", True)

    data = simulate(args.keyframes, np.random.default_rng(args.seed))
    imu_params = params()
    start = time.perf_counter()
    pim = jax.block_until_ready(preintegrate_all(data, imu_params, args.combined))
    preintegrated = time.perf_counter() - start
    pim, covariance = pim if args.combined else (pim, None)
    graph, _ = build_graph(data, pim, imu_params, covariance)
    from lieax.lstsq import Termination

    start = time.perf_counter()
    result = graph.solve(termination=Termination.gtsam(max_iterations=50))
    solved = time.perf_counter() - start
    summary = {
        "status": result.status_name,
        "iterations": int(result.iterations),
        "initial_cost": float(result.cost_history[0]),
        "cost": float(result.cost),
        **errors(data, result.values),
    }
    print(f"preintegrated {args.keyframes - 1} intervals x {RATE} samples in {preintegrated:.2f} s")
    print(
        f"solved in {solved:.2f} s: {summary['status']} after {summary['iterations']} "
        f"iterations, cost {summary['initial_cost']:.4g} -> {summary['cost']:.4g}"
    )
    print(
        f"rms errors: position {summary['position_rms']:.3f} m (fixes {summary['fix_rms']:.3f} m), "
        f"velocity {summary['velocity_rms']:.3f} m/s, attitude {summary['attitude_rms_deg']:.3f} deg, "
        f"accel bias {summary['accel_bias_rms']:.4f} m/s², gyro bias {summary['gyro_bias_rms']:.5f} rad/s"
    )
    if args.plot:
        plot(args.plot, data, result.values)
    return summary


if __name__ == "__main__":
    main()
