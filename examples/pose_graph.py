"""Optimize a pose graph from a g2o file with `lieax.graph.optimize` (Levenberg-Marquardt on the
block-sparse normal equations), print the cost per iteration, and save a before/after plot.

Without `--g2o` a graph is generated with a known ground truth, written to a g2o file and read
back: in 2D a robot driving on a grid of 1 m streets, closing loops where it passes a place
again (like M3500), in 3D a robot spiralling around a sphere, each ring tied to the previous
one (like sphere2500). Odometry and loop closures carry Gaussian noise (5 cm, 1 degree); the
initial poses are the odometry composed (dead reckoning), so they drift.

    python examples/pose_graph.py [--dim 3] [--poses 2500] [--plot graph.png]
    python examples/pose_graph.py --g2o $LIEAX_DATA_DIR/g2o/intel.g2o --plot intel.png

The first pose is held fixed (the gauge), unless the file fixes or anchors others.
"""

import argparse
import pathlib
import tempfile
import time

import jax
import jax.numpy as jnp
import numpy as np

SIGMA_TRANSLATION = 0.05  # m
SIGMA_ROTATION = np.deg2rad(1.0)


# ---- generated graphs -----------------------------------------------------------------------------


def grid_world(poses, rng):
    """`(truth SE2 (n,), edges (m, 2))`: a walk on a grid of 1 m streets, a turn of ±90° with
    probability 0.3 at every crossing, kept inside a square; an edge to the latest earlier visit
    of the same crossing (a loop closure) when one is more than 10 steps back."""
    import lieax

    side = max(4, int(np.sqrt(poses) / 1.5))
    x, y, heading = 0, 0, 0
    xy, theta = [], []
    for _ in range(poses):
        xy.append((x, y))
        theta.append(heading * np.pi / 2)
        if rng.uniform() < 0.3:
            heading = (heading + rng.choice([-1, 1])) % 4
        dx, dy = [(1, 0), (0, 1), (-1, 0), (0, -1)][heading]
        if not (0 <= x + dx < side and 0 <= y + dy < side):  # turn around at the border
            heading = (heading + 2) % 4
            dx, dy = -dx, -dy
        x, y = x + dx, y + dy
    xy, theta = np.array(xy, float), np.array(theta)
    edges = [(k, k + 1) for k in range(poses - 1)]
    last_visit = {}
    for k, cell in enumerate(map(tuple, xy.astype(int))):
        if cell in last_visit and k - last_visit[cell] > 10:
            edges.append((last_visit[cell], k))
        last_visit[cell] = k
    truth = lieax.SE2.from_xy_theta(
        jnp.asarray(xy[:, 0]), jnp.asarray(xy[:, 1]), jnp.asarray(theta)
    )
    return truth, np.array(edges)


def sphere_world(poses, rng):
    """`(truth SE3 (n,), edges (m, 2))`: `rings` rings of `per_ring` poses on a sphere of radius
    10 m, the robot facing along each ring; odometry along the spiral and an edge from every pose
    to the one below it on the previous ring."""
    import lieax

    per_ring = max(4, round(float(np.sqrt(poses))))
    rings = max(2, poses // per_ring)
    n = rings * per_ring
    k = np.arange(n)
    azimuth = 2 * np.pi * (k % per_ring) / per_ring
    polar = np.pi * (k // per_ring + 0.5) / rings
    position = 10.0 * np.stack(
        [np.sin(polar) * np.cos(azimuth), np.sin(polar) * np.sin(azimuth), np.cos(polar)], 1
    )
    forward = np.stack([-np.sin(azimuth), np.cos(azimuth), np.zeros(n)], 1)  # along the ring
    up = position / 10.0
    left = np.cross(up, forward)
    rotation = np.stack([forward, left, up], axis=2)  # columns: body x, y, z in the world
    truth = lieax.SE3.from_rotation_and_translation(
        lieax.SO3.from_matrix(jnp.asarray(rotation)), jnp.asarray(position)
    )
    edges = [(a, a + 1) for a in range(n - 1)]
    edges += [(a - per_ring, a) for a in range(per_ring, n)]
    return truth, np.array(edges)


def generate(dim, poses, seed=0):
    """A `PoseGraph` with noisy measurements and dead-reckoning initial poses, and the truth."""
    from lieax import graph

    rng = np.random.default_rng(seed)
    truth, edges = (grid_world if dim == 2 else sphere_world)(poses, rng)
    group = type(truth)
    d = group.tangent_dim
    sigma = np.array([SIGMA_TRANSLATION] * dim + [SIGMA_ROTATION] * (d - dim))
    i, j = edges[:, 0], edges[:, 1]
    noise = jnp.asarray(rng.normal(size=(len(edges), d)) * sigma)
    measured = truth[i].between(truth[j]).rplus(noise)
    information = np.diag(1.0 / sigma**2)
    odometry = np.abs(i - j) == 1  # dead reckoning: compose the odometry from the first pose
    steps = measured[jnp.asarray(np.nonzero(odometry)[0])]
    initial = [truth[0]]
    for k in range(steps.batch_shape[0]):
        initial.append(initial[-1] @ steps[k])
    initial = group(jnp.stack([pose.parameters() for pose in initial]))
    return graph.PoseGraph.create(initial, edges, measured, information), truth


# ---- reporting ------------------------------------------------------------------------------------


def position_rmse(poses, truth):
    """RMS distance between estimated and true positions (both anchored at the first pose)."""
    difference = np.asarray(poses.translation()) - np.asarray(truth.translation())
    return float(np.sqrt(np.mean(np.sum(difference**2, axis=-1))))


def save_plot(path, graph, result):
    """The graph at its initial poses and at the optimized ones, side by side."""
    from matplotlib.figure import Figure

    from lieax import viz

    figure = Figure(figsize=(10, 4.8), dpi=100)
    projection = "3d" if graph.dim == 3 else None
    for k, (title, poses) in enumerate((("initial", graph.poses), ("optimized", result.poses))):
        ax = figure.add_subplot(1, 2, k + 1, projection=projection)
        viz.plot_pose_graph(graph, poses, ax=ax)
        ax.set_title(f"{title}: cost {result.cost_history[0 if k == 0 else -1]:.4g}")
        ax.tick_params(labelsize=7)
    figure.tight_layout()
    figure.savefig(path)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--g2o", help="a g2o file (default: a generated graph)")
    parser.add_argument(
        "--dim", type=int, choices=(2, 3), default=2, help="generated graph: 2D or 3D"
    )
    parser.add_argument("--poses", type=int, default=500, help="generated graph: number of poses")
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument(
        "--init",
        choices=("file", "chordal"),
        default="file",
        help="initial poses: the file's, or chordal initialization",
    )
    parser.add_argument("--solver", choices=("cholesky", "cg"), default="cholesky")
    parser.add_argument("--max-iterations", type=int, default=100)
    parser.add_argument(
        "--verbose", action="store_true", help="print every attempt from inside the compiled loop"
    )
    parser.add_argument("--plot", help="save a before/after figure to this file (needs matplotlib)")
    args = parser.parse_args(argv)
    jax.config.update("jax_enable_x64", True)
    from lieax import graph
    from lieax.lstsq import Termination

    truth = None
    if args.g2o:
        pose_graph = graph.read_g2o(args.g2o)
        origin = args.g2o
    else:
        generated, truth = generate(args.dim, args.poses, args.seed)
        with tempfile.TemporaryDirectory() as folder:  # exercise the g2o writer and reader
            path = pathlib.Path(folder) / "generated.g2o"
            graph.write_g2o(path, generated)
            pose_graph = graph.read_g2o(path)
        origin = f"generated {args.dim}D graph (written to g2o and read back)"
    if args.init == "chordal":
        pose_graph = pose_graph.with_poses(graph.chordal_initialization(pose_graph))

    start = time.perf_counter()
    result = graph.optimize(
        pose_graph,
        linear_solver=args.solver,
        termination=Termination.gtsam(max_iterations=args.max_iterations),
        verbose=args.verbose,
    )
    first = time.perf_counter() - start
    start = time.perf_counter()
    result = graph.optimize(
        pose_graph,
        linear_solver=args.solver,
        termination=Termination.gtsam(max_iterations=args.max_iterations),
    )
    second = time.perf_counter() - start

    print(f"{origin}: {pose_graph!r}, initial poses: {args.init}")
    print(f"{'iteration':>9}  {'cost':>14}  {'decrease':>9}")
    history = result.cost_history
    for k, cost in enumerate(history):
        decrease = "" if k == 0 else f"{(history[k - 1] - cost) / history[k - 1]:9.2e}"
        print(f"{k:>9d}  {cost:>14.6f}  {decrease:>9}")
    print(
        f"{result.status.name} after {result.iterations} iterations ({result.linear_solves} "
        f"linear solves), solver {args.solver}"
    )
    print(f"time: {first:.2f} s first call (with compilation), {second:.3f} s second call")
    summary = {
        "initial_cost": float(history[0]),
        "cost": result.cost,
        "status": result.status.name,
        "iterations": result.iterations,
    }
    if truth is not None:
        before, after = position_rmse(pose_graph.poses, truth), position_rmse(result.poses, truth)
        print(f"position RMSE vs truth: {before:.3f} m initial, {after:.3f} m optimized")
        summary.update(rmse_initial=before, rmse=after)
    if args.plot:
        save_plot(args.plot, pose_graph, result)
        print(f"saved {args.plot}")
    return summary


if __name__ == "__main__":
    main()
