"""Batched ICP benchmark: many registrations in one `vmap`ped `lieax.icp.point_to_plane` call,
against Open3D's `registration_icp` in a Python loop and against a loop of single lieax calls.

On every kind of scan of `benchmarks/neighbors.py` (the bunny at 2 mm, outdoor LiDAR, the Kinect
frame; radii 1 cm, 1 m, 5 cm; Open3D's target normals given to both), two batches of `--count`:

- "starts": one pair from `count` initial guesses, rotations of up to 5° and translations of up to
  half the radius about the identity (every element shares the target, so one host k-d tree);
- "pairs": `count` different pairs, each a random 90% of the source and 90% of the target (a
  tree per target), padded to one size with `icp.pad_clouds`, from the identity.

float32 (the dtype of a batch on an accelerator), Open3D's criteria (1e-6, cap 30), every variant
compiled and warmed up, then timed interleaved (medians). Columns: the three wall times, the batch's
speed-up over each loop, its compile time, and the lockstep idling: under `vmap` the loop runs
until its slowest element stops, so `1 - mean/max` of the elements' iterations is the share of
element-iterations spent waiting (an element that has stopped sends no queries to the tree, but its
share of the compiled arithmetic still runs). The agreement column compares each lieax result with
Open3D's from the same start (median / max rotation gap).

Run `LIEAX_DATA_DIR=../shared/data python benchmarks/icp_batch.py` (the `bench` extra).
"""

import argparse
import os
import sys

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
import _environment

_environment.passive_openmp()  # before Open3D loads its OpenMP runtime

import jax

jax.config.update("jax_enable_x64", True)

import jax.numpy as jnp
import neighbors
import numpy as np
import open3d as o3d
from _timing import (
    format_ratio,
    format_seconds,
    machine_description,
    markdown_table,
    time_interleaved,
)
from icp import SCAN_NORMALS, open3d_cloud, rotation_deg, scan_normals, timed

from lieax import SE3, icp

TOLERANCE, CAP = 1e-6, 30
KEEP = 0.9  # share of each cloud kept in a "pairs" element


def perturbations(count, seed, degrees, metres):
    """`count` SE3 parameter rows: rotations of up to `degrees` about random axes, translations of
    up to `metres` in random directions."""
    rng = np.random.default_rng(seed)
    axes = rng.normal(size=(count, 3))
    axes /= np.linalg.norm(axes, axis=1, keepdims=True)
    directions = rng.normal(size=(count, 3))
    directions /= np.linalg.norm(directions, axis=1, keepdims=True)
    omega = axes * np.deg2rad(rng.uniform(0, degrees, (count, 1)))
    v = directions * rng.uniform(0, metres, (count, 1))
    return np.asarray(SE3.exp(jnp.asarray(np.concatenate([v, omega], axis=1))).parameters())


def starts_batch(source, target, normals, radius, count):
    """`count` elements: the pair itself from perturbed starts."""
    inits = perturbations(count, seed=7, degrees=5.0, metres=radius / 2)
    return [(source, target, normals, init) for init in inits]


def pairs_batch(source, target, normals, radius, count):
    """`count` elements: random 90% subsets of both clouds, from the identity."""
    rng = np.random.default_rng(11)
    identity = np.asarray([1.0, 0, 0, 0, 0, 0, 0])
    elements = []
    for _ in range(count):
        s = np.sort(rng.choice(len(source), int(KEEP * len(source)), replace=False))
        t = np.sort(rng.choice(len(target), int(KEEP * len(target)), replace=False))
        elements.append((source[s], target[t], normals[t], identity))
    return elements


def run_batch(label, elements, radius, rounds):
    """Time the three variants on `elements` `[(source, target, normals, init)]`; a table row."""
    sources, source_mask = icp.pad_clouds([e[0] for e in elements], dtype=np.float32)
    targets, target_mask = icp.pad_clouds([e[1] for e in elements], dtype=np.float32)
    normals, _ = icp.pad_clouds([e[2] for e in elements], dtype=np.float32)
    inits = jnp.asarray(np.stack([e[3] for e in elements]), jnp.float32)

    def register(s, sm, t, tm, n, init):
        return icp.point_to_plane(
            s, t, source_mask=sm, target_mask=tm, target_normals=n, init=SE3(init),
            max_correspondence_distance=radius, relative_fitness=TOLERANCE,
            relative_rmse=TOLERANCE, max_iterations=CAP,
        )  # fmt: skip

    batched = jax.jit(jax.vmap(register))
    mapped = jax.jit(lambda *a: jax.lax.map(lambda x: register(*x), a))
    single = jax.jit(register)
    arguments = (sources, source_mask, targets, target_mask, normals, inits)
    singles = [tuple(a[i] for a in arguments) for i in range(len(elements))]

    estimation = o3d.pipelines.registration.TransformationEstimationPointToPlane()
    criteria = o3d.pipelines.registration.ICPConvergenceCriteria(TOLERANCE, TOLERANCE, CAP)
    o3d_pairs = [
        (
            open3d_cloud(e[0]),
            open3d_cloud(e[1], e[2]),
            np.asarray(SE3(jnp.asarray(e[3])).as_matrix()),
        )
        for e in elements
    ]

    def open3d_loop():
        return [
            o3d.pipelines.registration.registration_icp(s, t, radius, start, estimation, criteria)
            for s, t, start in o3d_pairs
        ]

    variants = {
        "open3d loop": timed(open3d_loop),
        "lieax loop": lambda: [single(*a) for a in singles],
        "lieax vmap": lambda: batched(*arguments),
        "lieax map": lambda: mapped(*arguments),
    }
    timings = time_interleaved(variants, rounds, warmup=1, min_sample_s=0)
    results = batched(*arguments)
    iterations = np.asarray(results.iterations)
    poses = np.asarray(results.transform.as_matrix(), np.float64)
    gaps = [rotation_deg(p, np.asarray(r.transformation)) for p, r in zip(poses, open3d_loop())]
    statuses = dict(zip(*np.unique(np.asarray(results.status_name), return_counts=True)))
    median = {k: t.median for k, t in timings.items()}
    row = [
        label, f"{len(elements)} × {sources.shape[1]}/{targets.shape[1]}",
        format_seconds(median["open3d loop"]), format_seconds(median["lieax loop"]),
        format_seconds(median["lieax vmap"]), format_seconds(median["lieax map"]),
        format_ratio(median["open3d loop"], median["lieax vmap"]),
        format_ratio(median["lieax loop"], median["lieax vmap"]),
        f"{timings['lieax vmap'].compile_s:.1f} s",
        f"{1 - iterations.mean() / iterations.max():.2f} ({iterations.min()}–{iterations.max()})",
        f"{np.median(gaps):.4f}° / {np.max(gaps):.4f}°",
    ]  # fmt: skip
    note = f"{label}: statuses {statuses}"
    return row, note


def main():
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    _environment.add_data_dir(parser)
    parser.add_argument("--rounds", type=int, default=3)
    parser.add_argument("--count", type=int, default=64)
    parser.add_argument("--clouds", default="bunny 2 mm,LiDAR,Kinect")
    parser.add_argument("--batches", default="starts,pairs")
    args = parser.parse_args()
    print("# Batched ICP benchmark\n")
    print(machine_description(), "\n")
    clouds = neighbors.load_clouds(args.data_dir)
    makers = {"starts": starts_batch, "pairs": pairs_batch}
    rows, notes = [], []
    for label in args.clouds.split(","):
        source, target, radius, _ = clouds[label]
        normals = scan_normals(target, SCAN_NORMALS[label])
        for kind in args.batches.split(","):
            elements = makers[kind](source, target, normals, radius, args.count)
            row, note = run_batch(f"{label}, {kind}", elements, radius, args.rounds)
            rows.append(row)
            notes.append(note)
            print(markdown_table(HEADERS, [row]), flush=True)
    print("\n## Every batch\n")
    print(markdown_table(HEADERS, rows))
    print("\n" + "\n".join(f"- {n}" for n in notes))


HEADERS = [
    "batch", "registrations × points", "Open3D loop", "lieax loop", "lieax vmap", "lieax lax.map",
    "vmap vs Open3D", "vmap vs lieax loop", "vmap compile", "lockstep idle (iterations)",
    "vs Open3D (median / max)",
]  # fmt: skip

if __name__ == "__main__":
    main()
