"""Register many pairs of point clouds in one `vmap`ped, jitted ICP call, and report throughput.

Each pair is two independent scans of the generated scene (its own samples, its own noise)
related by its own random motion; the clouds have different sizes, so they are padded to one
shape with `lieax.icp.pad_clouds` and the padding is masked out. The batch is registered by
`jax.vmap` of `lieax.icp.point_to_plane` (compiled once for the batch; every pair stops on its
own criteria, the batch runs until the last one has), and, for comparison, pair by pair with the
single-pair function (compiled once for the padded shape). Both must give the same transforms.

    python examples/batch_icp.py [--pairs 64] [--points 2000] [--rotation 15]
"""

import argparse
import time

import jax
import jax.numpy as jnp
import numpy as np

from lieax import icp


def make_pairs(pairs, points, rotation_deg, translation, noise, seed):
    """`pairs` generated pairs with sizes between 80% and 100% of `points`, padded:
    `(sources, source_masks, targets, target_masks, target_normals, truths)`."""
    rng = np.random.default_rng(seed)
    sources, targets, normals, truths = [], [], [], []
    for k in range(pairs):
        size = int(points * rng.uniform(0.8, 1.0))
        source, target, target_normals, truth = icp.synthetic_pair(
            size, rotation_deg=rotation_deg * rng.uniform(0.5, 1.0),
            translation=translation * rng.uniform(0.5, 1.0), noise=noise, same_samples=False,
            seed=seed + 7919 * k,
        )  # fmt: skip
        sources.append(source)
        targets.append(target)
        normals.append(target_normals)
        truths.append(truth.parameters())
    source, source_mask = icp.pad_clouds(sources, points)
    target, target_mask = icp.pad_clouds(targets, points)
    target_normals, _ = icp.pad_clouds(normals, points)
    return source, source_mask, target, target_mask, target_normals, jnp.stack(truths)


def main(argv=None):
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--pairs", type=int, default=32)
    parser.add_argument("--points", type=int, default=2000, help="points per cloud, at most")
    parser.add_argument("--rotation", type=float, default=15.0, help="largest rotation, degrees")
    parser.add_argument("--translation", type=float, default=0.2, help="largest translation, m")
    parser.add_argument("--noise", type=float, default=0.002, help="noise along normals, m")
    parser.add_argument("--max-distance", type=float, default=0.2)
    parser.add_argument("--seed", type=int, default=0)
    parser.add_argument("--no-loop", action="store_true", help="skip the pair-by-pair comparison")
    args = parser.parse_args(argv)
    jax.config.update("jax_enable_x64", True)

    import lieax  # after enabling float64

    data = make_pairs(
        args.pairs, args.points, args.rotation, args.translation, args.noise, args.seed
    )
    source, source_mask, target, target_mask, target_normals, truths = data

    def register(source, source_mask, target, target_mask, target_normals):
        return icp.point_to_plane(
            source, target, target_normals=target_normals, source_mask=source_mask,
            target_mask=target_mask, max_correspondence_distance=args.max_distance,
        )  # fmt: skip

    batched = jax.jit(jax.vmap(register))
    single = jax.jit(register)
    inputs = (source, source_mask, target, target_mask, target_normals)

    start = time.perf_counter()
    results = jax.block_until_ready(batched(*inputs))
    compile_and_run = time.perf_counter() - start
    start = time.perf_counter()
    results = jax.block_until_ready(batched(*inputs))
    batch_seconds = time.perf_counter() - start

    truth = lieax.SE3(truths)
    rotation_error = np.rad2deg(
        np.linalg.norm(np.asarray(results.transform.rotation().rminus(truth.rotation())), axis=-1)
    )
    translation_error = np.linalg.norm(
        np.asarray(results.transform.translation() - truth.translation()), axis=-1
    )
    names, counts = np.unique(np.asarray(results.status_name, dtype=str), return_counts=True)
    iterations = np.asarray(results.iterations)

    print(
        f"{args.pairs} pairs of generated scans, {args.points} points per cloud at most "
        f"(padded), rotations up to {args.rotation} deg, translations up to {args.translation} m"
    )
    print(
        f"status: {', '.join(f'{n} {s}' for s, n in zip(names, counts))}; iterations "
        f"{iterations.min()}-{iterations.max()} (the batch runs {iterations.max()})"
    )
    print(
        f"error vs truth: rotation max {rotation_error.max():.4f} deg, translation max "
        f"{translation_error.max() * 1e3:.3f} mm; fitness min {float(results.fitness.min()):.3f}"
    )
    print(
        f"vmapped: {batch_seconds * 1e3:.1f} ms for the batch, {args.pairs / batch_seconds:.1f} "
        f"pairs/s ({compile_and_run:.2f} s first call, with compilation)"
    )
    summary = {
        "max_rotation_error_deg": float(rotation_error.max()),
        "max_translation_error": float(translation_error.max()),
        "converged": int(np.sum(np.asarray(results.converged))),
        "batch_pairs_per_second": args.pairs / batch_seconds,
    }
    if not args.no_loop:
        jax.block_until_ready(single(*(x[0] for x in inputs)))  # compile
        start = time.perf_counter()
        looped = [single(*(x[k] for x in inputs)) for k in range(args.pairs)]
        jax.block_until_ready(looped)
        loop_seconds = time.perf_counter() - start
        looped_params = np.stack([np.asarray(r.transform.parameters()) for r in looped])
        difference = np.max(np.abs(looped_params - np.asarray(results.transform.parameters())))
        print(
            f"pair by pair: {loop_seconds * 1e3:.1f} ms, {args.pairs / loop_seconds:.1f} pairs/s; "
            f"vmapped/looped time ratio {batch_seconds / loop_seconds:.2f}; largest parameter "
            f"difference {difference:.1e}"
        )
        summary.update(
            loop_pairs_per_second=args.pairs / loop_seconds,
            max_difference_to_loop=float(difference),
        )
    return summary


if __name__ == "__main__":
    main()
