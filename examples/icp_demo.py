"""Register two point clouds with lieax's ICP and check the result.

By default the clouds are generated: two independent scans (own samples, own noise) of a room
corner with a sphere and a cylinder, related by a known rigid motion, so the estimate can be
compared with the truth. `--source`/`--target` register files instead (`.ply`, `.pcd`, `.npy`,
`.npz`, `.xyz`/`.txt`; the target's normals are used when the file has them); `--pair` reads
one `.npz` holding `source`, `target` and optionally the reference `T_target_source`, as the
shared data's bunny files do:

    python examples/icp_demo.py
    python examples/icp_demo.py --pair $LIEAX_DATA_DIR/clouds/bunny_045_to_000/bunny_v0.002.npz
    python examples/icp_demo.py --source bun045.ply --target bun000.ply --voxel 0.002 --plot icp.png --up y

The result is `T_target_source` (an `SE3` mapping source coordinates into the target frame),
with the fitness (fraction of source points within `--max-distance` of the target), the inlier
RMSE, the iterations and the time: the first call includes compilation, the second is the
registration alone.
"""

import argparse
import pathlib
import time

import jax
import jax.numpy as jnp
import numpy as np

import lieax
from lieax import icp

# ---- reading clouds -------------------------------------------------------------------------------


def read_cloud(path):
    """`(points (n, 3), normals (n, 3) or None)` from a `.ply`, `.pcd`, `.npy` or `.npz` file
    (`lieax.read_point_cloud`), or from a text file of rows `x y z ...` (`.xyz`, `.txt`, `.csv`)."""
    path = pathlib.Path(path)
    if path.suffix.lower() in (".ply", ".pcd", ".npy", ".npz"):
        cloud = lieax.read_point_cloud(path)
        return cloud.points, cloud.normals
    rows = np.loadtxt(path, ndmin=2, delimiter="," if path.suffix.lower() == ".csv" else None)
    if rows.shape[1] < 3:
        raise ValueError(f"{path}: expected rows of at least 3 numbers, got {rows.shape[1]}.")
    return rows[:, :3], None


# ---- reporting ------------------------------------------------------------------------------------


def describe(T):
    """`rotation θ° about axis, translation t` of an SE3."""
    omega = np.asarray(T.rotation().log())
    angle = np.linalg.norm(omega)
    axis = omega / angle if angle > 0 else np.array([0.0, 0.0, 1.0])
    with np.printoptions(precision=4, suppress=True, sign=" "):
        return (
            f"rotation {np.rad2deg(angle):7.3f} deg about {axis}, "
            f"translation {np.asarray(T.translation())}"
        )


def pose_error(T_estimate, T_reference):
    """Rotation error (deg) and translation error of `T_estimate` against `T_reference`."""
    rotation = np.rad2deg(
        np.linalg.norm(np.asarray(T_estimate.rotation().rminus(T_reference.rotation())))
    )
    translation = np.linalg.norm(np.asarray(T_estimate.translation() - T_reference.translation()))
    return float(rotation), float(translation)


def save_plot(path, source, target, T_target_source, up="z", max_points=4000):
    """Before (source as given) and after (source mapped by the estimate), side by side, with
    axis `up` drawn vertical."""
    from matplotlib.figure import Figure

    from lieax import viz

    figure = Figure(figsize=(10, 4.8), dpi=100)
    for k, (title, transform) in enumerate((("before", None), ("after ICP", T_target_source))):
        ax = figure.add_subplot(1, 2, k + 1, projection="3d")
        viz.plot_registration(source, target, transform, ax=ax, max_points=max_points, title=title)
        ax.view_init(elev=20, azim=-60 if up == "z" else 30, vertical_axis=up)
        ax.tick_params(labelsize=6)
        ax.legend(loc="upper right", markerscale=6)
    figure.tight_layout()
    figure.savefig(path)


# ---- main -----------------------------------------------------------------------------------------


def main(argv=None):
    parser = argparse.ArgumentParser(
        description=__doc__.split("\n\n")[0], formatter_class=argparse.RawDescriptionHelpFormatter
    )
    data = parser.add_argument_group("data (generated unless files are given)")
    data.add_argument("--source", help="source cloud file (.ply, .pcd, .npy, .npz, .xyz, .txt)")
    data.add_argument("--target", help="target cloud file")
    data.add_argument("--pair", help=".npz with source, target and optionally T_target_source")
    data.add_argument("--points", type=int, default=4000, help="generated points per cloud")
    data.add_argument("--rotation", type=float, default=15.0, help="generated rotation, degrees")
    data.add_argument("--translation", type=float, default=0.2, help="generated translation, m")
    data.add_argument("--noise", type=float, default=0.002, help="generated noise along normals, m")
    data.add_argument("--seed", type=int, default=0)
    options = parser.add_argument_group("registration")
    options.add_argument(
        "--method",
        choices=("plane", "point"),
        default="plane",
        help="point-to-plane (default) or point-to-point",
    )
    options.add_argument(
        "--max-distance",
        type=float,
        default=None,
        help="max correspondence distance (default 5%% of the target's extent)",
    )
    options.add_argument("--voxel", type=float, default=None, help="downsample both clouds first")
    options.add_argument("--max-iterations", type=int, default=30)
    options.add_argument("--float32", action="store_true", help="register in float32")
    parser.add_argument("--plot", help="save a before/after figure to this file (needs matplotlib)")
    parser.add_argument(
        "--up",
        choices=("x", "y", "z"),
        default="z",
        help="the plot's vertical axis (the bunny scans have y up)",
    )
    args = parser.parse_args(argv)
    if (args.source is None) != (args.target is None):
        parser.error("--source and --target go together")
    jax.config.update("jax_enable_x64", not args.float32)
    dtype = jnp.float32 if args.float32 else jnp.float64

    T_reference, target_normals = None, None
    if args.pair:
        with np.load(args.pair) as pair:
            source, target = pair["source"], pair["target"]
            if "T_target_source" in pair.files:
                T_reference = lieax.SE3.from_matrix(np.asarray(pair["T_target_source"], dtype))
        origin = args.pair
    elif args.source:
        (source, _), (target, target_normals) = read_cloud(args.source), read_cloud(args.target)
        origin = f"{args.source} -> {args.target}"
    else:
        source, target, target_normals, T_reference = icp.synthetic_pair(
            args.points, rotation_deg=args.rotation, translation=args.translation,
            noise=args.noise, same_samples=False, seed=args.seed, dtype=dtype,
        )  # fmt: skip
        origin = (
            f"generated scene, {args.points} points per cloud, independent samples, "
            f"noise {args.noise} m"
        )
    # NumPy until the registration: eager jax.numpy would compile a small program per operation
    source, target = np.asarray(source, dtype), np.asarray(target, dtype)
    if args.voxel:
        source = icp.voxel_downsample(source, args.voxel)
        target = icp.voxel_downsample(target, args.voxel)
        target_normals = None  # estimated on the downsampled target
    corners = np.asarray(target)
    extent = float(np.linalg.norm(corners.max(0) - corners.min(0)))
    max_distance = args.max_distance or 0.05 * extent

    def register():
        if args.method == "plane":
            return icp.point_to_plane(
                source, target, target_normals=target_normals, max_correspondence_distance=max_distance,
                max_iterations=args.max_iterations,
            )  # fmt: skip
        return icp.point_to_point(
            source, target, max_correspondence_distance=max_distance,
            max_iterations=args.max_iterations,
        )  # fmt: skip

    start = time.perf_counter()
    result = jax.block_until_ready(register())
    first = time.perf_counter() - start
    start = time.perf_counter()
    result = jax.block_until_ready(register())
    second = time.perf_counter() - start
    T = result.transform

    print(f"data: {origin}")
    print(
        f"source {source.shape[0]} points, target {target.shape[0]} points, "
        f"point-to-{args.method}, max correspondence distance {max_distance:.4g}, {dtype.__name__}"
    )
    if T_reference is not None:
        print(f"true      T_target_source: {describe(T_reference)}")
    print(f"estimated T_target_source: {describe(T)}")
    with np.printoptions(precision=5, suppress=True):
        print(f"estimated matrix:\n{np.asarray(T.as_matrix())}")
    summary = {
        "status": result.status_name,
        "fitness": float(result.fitness),
        "inlier_rmse": float(result.inlier_rmse),
        "iterations": int(result.iterations),
        "seconds": second,
    }
    if T_reference is not None:
        rotation_error, translation_error = pose_error(T, T_reference)
        summary.update(rotation_error_deg=rotation_error, translation_error=translation_error)
        print(
            f"error vs truth: rotation {rotation_error:.4f} deg, translation "
            f"{translation_error:.3g} ({translation_error / extent:.2e} of the target's extent)"
        )
    print(
        f"{result.status_name} after {int(result.iterations)} iterations: fitness "
        f"{float(result.fitness):.4f}, inlier RMSE {float(result.inlier_rmse):.4g}"
    )
    print(f"time: {first:.2f} s first call (with compilation), {second * 1e3:.1f} ms second call")
    if args.plot:
        save_plot(args.plot, np.asarray(source), np.asarray(target), T, up=args.up)
        print(f"saved {args.plot}")
    return summary


if __name__ == "__main__":
    main()
