"""Tests of lieax.icp: nearest neighbours, normals, downsampling, point-to-point and point-to-plane
ICP, batching over padded pairs, bad input; real scans when `LIEAX_DATA_DIR` is set.

Compilation dominates the cost of these tests, so every synthetic cloud is padded to `ROWS` rows
(masked): the ICP loops compile once per (kind, dtype) and every test reuses them.
"""

import os

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from lieax import SE3, icp
from lieax.icp import _loop
from lieax.lstsq import Cauchy, Huber

ROWS = 400  # rows of every padded synthetic cloud (>= the PCL bunny pair's 397 points)
RADIUS = 0.4  # max_correspondence_distance on the synthetic scene (about 2 m across)
DATA_DIR = os.environ.get("LIEAX_DATA_DIR")


def padded(points, rows=ROWS):
    points = np.asarray(points)
    out = np.zeros((rows, 3), points.dtype)
    out[: len(points)] = points
    mask = np.arange(rows) < len(points)
    return jnp.asarray(out), jnp.asarray(mask)


def pose_error(estimate: SE3, truth: SE3):
    """(rotation error in radians, translation error) between two poses."""
    xi = np.asarray(truth.inverse().compose(estimate).log())
    return float(np.linalg.norm(xi[3:])), float(
        np.linalg.norm(np.asarray(estimate.translation() - truth.translation()))
    )


def brute_force(queries, target):
    d2 = np.sum((np.asarray(queries)[:, None, :] - np.asarray(target)[None]) ** 2, axis=-1)
    index = np.argmin(d2, axis=1)
    return index, np.sqrt(d2[np.arange(len(index)), index])


def register(kind, source, target, normals=None, **kwargs):
    s, sm = padded(source)
    t, tm = padded(target)
    options = {"max_correspondence_distance": RADIUS, "source_mask": sm, "target_mask": tm}
    options.update(kwargs)
    if kind == "plane":
        return icp.point_to_plane(s, t, target_normals=padded(normals)[0], **options)
    return icp.point_to_point(s, t, **options)


@pytest.fixture(scope="module")
def pair():
    return icp.synthetic_pair(380, rotation_deg=8.0, translation=0.08, seed=3)


# ---- normals and downsampling -------------------------------------------------------------------


def test_estimate_normals_match_pca_and_the_surfaces():
    points, normals = icp.synthetic_scene(1500, seed=5)
    viewpoint = np.array([0.2, 0.3, 5.0])
    estimated = np.asarray(icp.estimate_normals(points, k=12, viewpoint=tuple(viewpoint)))
    # The closed-form eigenvector equals NumPy's PCA over the same 12 nearest neighbours.
    p = np.asarray(points)
    neighbours = np.argsort(np.sum((p[:, None] - p[None]) ** 2, axis=-1), axis=1)[:, :12]
    centred = p[neighbours] - p[neighbours].mean(axis=1, keepdims=True)
    reference = np.linalg.eigh(np.einsum("nki,nkj->nij", centred, centred))[1][:, :, 0]
    assert np.median(np.abs(np.sum(estimated * reference, axis=1))) > 1 - 1e-9
    assert np.mean(np.abs(np.sum(estimated * reference, axis=1)) > 0.999) > 0.98
    np.testing.assert_allclose(np.linalg.norm(estimated, axis=1), 1.0, atol=1e-9)
    # Away from edges the normals are the surfaces'; all face the viewpoint.
    agreement = np.abs(np.sum(estimated * np.asarray(normals), axis=1))
    assert np.median(agreement) > 0.99
    assert np.all(np.sum(estimated * (viewpoint - p), axis=1) >= 0)


def test_voxel_downsample_matches_a_reference():
    rng = np.random.default_rng(2)
    points = rng.uniform(0, 1, (500, 3))
    size = 0.15
    out = np.asarray(icp.voxel_downsample(jnp.asarray(points), size))
    lowest = points.min(axis=0) - size / 2
    cells = {}
    for p in points:
        cells.setdefault(tuple(np.floor((p - lowest) / size).astype(int)), []).append(p)
    expected = np.array([np.mean(cells[key], axis=0) for key in sorted(cells)])
    np.testing.assert_allclose(out, expected, atol=1e-12)
    fixed, mask = icp.voxel_downsample(jnp.asarray(points), size, size=600)
    assert fixed.shape == (600, 3) and int(mask.sum()) == len(expected)
    np.testing.assert_allclose(np.asarray(fixed)[np.asarray(mask)], expected, atol=1e-12)


def test_pad_clouds():
    points, mask = icp.pad_clouds([np.ones((2, 3)), np.zeros((4, 3))])
    assert points.shape == (2, 4, 3)
    np.testing.assert_array_equal(np.asarray(mask), [[1, 1, 0, 0], [1, 1, 1, 1]])
    with pytest.raises(ValueError, match="smaller than the largest"):
        icp.pad_clouds([np.ones((5, 3))], size=3)


# ---- registration -------------------------------------------------------------------------------


ROTATIONS = {  # the standards' poses: identity, 1e-9 and 1e-4 rad, pure translation, near pi
    "identity": (0.0, [0.0, 0.0, 0.0]),
    "1e-9": (1e-9, [0.3, -0.2, 0.5]),
    "1e-4": (1e-4, [0.3, -0.2, 0.5]),
    "translation": (0.0, [1.5, -0.7, 2.0]),
    "pi-1e-4": (np.pi - 1e-4, [0.3, -0.2, 0.5]),
    "pi-1e-6": (np.pi - 1e-6, [0.3, -0.2, 0.5]),
    "random": (2.1, [-0.4, 0.9, 0.1]),
}


def _se3_exp_matrix(xi):
    """NumPy $\\mathrm{Exp}$ of an SE(3) tangent $(v, \\omega)$ as a 4x4 matrix: Rodrigues'
    rotation and $V(\\omega) v$ (Solà et al. 2018, appendix D), for finite differences."""
    v, w = xi[:3], xi[3:]
    theta = np.linalg.norm(w)
    k = np.array([[0, -w[2], w[1]], [w[2], 0, -w[0]], [-w[1], w[0], 0]])
    a = np.sinc(theta / np.pi)  # sin(theta) / theta
    b = (1 - np.cos(theta)) / theta**2 if theta > 1e-4 else 0.5 - theta**2 / 24
    c = (theta - np.sin(theta)) / theta**3 if theta > 1e-4 else 1 / 6 - theta**2 / 120
    out = np.eye(4)
    out[:3, :3] = np.eye(3) + a * k + b * k @ k
    out[:3, 3] = (np.eye(3) + b * k + c * k @ k) @ v
    return out


def test_plane_rows_match_lieax_jacobian_and_finite_differences():
    """`_plane_rows`' closed form $[R^T n, s \\times R^T n]$ equals $n^T$ times `lieax.jacobian`
    of `SE3`'s action, and central differences of $n^T (T \\,\\mathrm{Exp}(\\xi)) s$ in the
    right tangent (float64), at every pose of `ROTATIONS`, batched over the poses and unbatched."""
    from lieax import jacobian
    from lieax.icp._plane_step import plane_rows as _plane_rows

    rng = np.random.default_rng(11)
    points = rng.normal(size=(5, 3)) * 2.0
    normals = rng.normal(size=(5, 3))
    normals /= np.linalg.norm(normals, axis=1, keepdims=True)
    axis = np.array([0.48, -0.6, 0.64])
    tangents = jnp.asarray([np.concatenate([t, a * axis]) for a, t in ROTATIONS.values()])
    act = jax.vmap(jacobian(lambda T, p: T @ p), in_axes=(None, 0))

    @jax.jit
    @jax.vmap
    def rows_and_reference(tangent):
        pose = SE3.exp(tangent)
        rows = _plane_rows(pose.parameters(), points, normals).T  # (6, n): transposed rows
        reference = jnp.einsum("na,nab->nb", normals, act(pose, jnp.asarray(points)))
        return pose.as_matrix(), pose.parameters(), rows, reference

    matrices, params, rows, reference = (np.asarray(x) for x in rows_and_reference(tangents))
    np.testing.assert_allclose(rows, reference, rtol=0, atol=1e-12)
    step = 1e-6
    homogeneous = np.concatenate([points, np.ones((5, 1))], axis=1)
    for matrix, pose_rows in zip(matrices, rows):

        def residual(xi, matrix=matrix):
            return np.sum(normals * (matrix @ _se3_exp_matrix(xi) @ homogeneous.T).T[:, :3], 1)

        columns = [(residual(step * e) - residual(-step * e)) / (2 * step) for e in np.eye(6)]
        np.testing.assert_allclose(pose_rows, np.stack(columns, axis=1), rtol=0, atol=1e-8)
    single = jax.jit(_plane_rows)(params[-1], points, normals).T
    np.testing.assert_allclose(single, rows[-1], rtol=0, atol=1e-15)


def test_point_to_plane_recovers_the_motion(pair):
    source, target, normals, truth = pair
    result = register("plane", source, target, normals)
    rotation, translation = pose_error(result.transform, truth)
    assert result.status_name == "CONVERGED" and bool(result.converged)
    assert rotation < 1e-6 and translation < 1e-6
    assert float(result.fitness) == 1.0 and float(result.inlier_rmse) < 1e-6
    # Correspondences are the exact nearest neighbours at the final pose; padding has none.
    moved = np.asarray(result.transform @ source)
    index, _ = brute_force(moved, target)
    correspondences = np.asarray(result.correspondences)
    np.testing.assert_array_equal(correspondences[: len(source)], index)
    assert np.all(correspondences[len(source) :] == -1)


def test_point_to_point_recovers_the_motion(pair):
    source, target, _, truth = pair
    result = register("point", source, target)
    rotation, translation = pose_error(result.transform, truth)
    assert result.status_name == "CONVERGED"
    assert rotation < 1e-6 and translation < 1e-6


def test_verbose_prints_every_iteration_from_the_compiled_loop(pair, capfd):
    source, target, normals, _ = pair
    result = register("plane", source, target, normals, verbose=True)
    jax.effects_barrier()
    lines = [line for line in capfd.readouterr().out.splitlines() if "icp iteration" in line]
    assert len(lines) >= int(result.iterations)
    assert f"fitness {float(result.fitness):.6f}" in lines[-1]


def test_fitness_and_rmse_are_open3d_definitions(pair):
    source, target, normals, _ = pair
    noisy_target = np.asarray(target) + np.random.default_rng(4).normal(size=target.shape) * 0.01
    result = register("plane", source, noisy_target, normals, max_correspondence_distance=0.05)
    moved = np.asarray(result.transform @ source)
    index, distance = brute_force(moved, noisy_target)
    inliers = distance <= 0.05
    assert float(result.fitness) == pytest.approx(inliers.mean(), abs=1e-12)
    assert float(result.inlier_rmse) == pytest.approx(
        np.sqrt(np.mean(distance[inliers] ** 2)), rel=1e-9
    )
    correspondences = np.asarray(result.correspondences)[: len(source)]
    np.testing.assert_array_equal(correspondences, np.where(inliers, index, -1))


def test_presample_reaches_the_direct_pose_and_batches():
    """`presample` (by default every 8th source point first, then all of them) converges to the
    pose of the direct run, compiles one loop for both stages, batches under `vmap`; 0 and
    `max_iterations=1` skip the first stage and a share outside [0, 1] is refused."""
    source, target, normals, truth = icp.synthetic_pair(4000, rotation_deg=8.0, translation=0.08)
    noisy = jnp.asarray(
        np.asarray(target) + np.random.default_rng(5).normal(size=target.shape) * 0.005
    )
    options = {
        "target_normals": normals, "max_correspondence_distance": RADIUS,
        "relative_fitness": 1e-12, "relative_rmse": 1e-12, "max_iterations": 60,
    }  # fmt: skip
    direct = icp.point_to_plane(source, noisy, presample=0, **options)
    compiled = _loop.solve._cache_size()
    staged = icp.point_to_plane(source, noisy, **options)
    assert _loop.solve._cache_size() == compiled  # (the direct run's loop, reused)
    assert direct.status_name == staged.status_name == "CONVERGED"
    rotation, translation = pose_error(staged.transform, direct.transform)
    assert rotation < 1e-9 and translation < 1e-9
    np.testing.assert_array_equal(staged.correspondences, direct.correspondences)
    inits = SE3.exp(jnp.asarray([[0.0] * 6, [0.02, -0.01, 0.0, 0.0, 0.03, -0.02]]))
    batched = jax.vmap(lambda init: icp.point_to_plane(source, noisy, init=init, **options))(inits)
    for i in range(2):
        rotation, translation = pose_error(batched.transform[i], direct.transform)
        assert rotation < 1e-9 and translation < 1e-9
    one_step = {**options, "max_iterations": 1}  # (stepping by hand: no first stage)
    stepped = icp.point_to_plane(source, noisy, **one_step)
    assert int(stepped.iterations) == 1
    rotation, translation = pose_error(
        stepped.transform, icp.point_to_plane(source, noisy, presample=0, **one_step).transform
    )
    assert rotation < 1e-12 and translation < 1e-12
    with pytest.raises(icp.ICPInputError, match="presample"):
        icp.point_to_plane(source, noisy, presample=1.5, **options)


def test_robust_loss_resists_outliers(pair):
    source, target, normals, truth = pair
    target = np.asarray(target).copy()
    rng = np.random.default_rng(6)
    outliers = rng.choice(len(target), 60, replace=False)
    target[outliers] += rng.normal(size=(60, 3)) * 0.1  # 15% of the target moved off its surface
    plain = register("plane", source, target, normals)
    robust = register("plane", source, target, normals, loss=Cauchy(0.01))
    assert pose_error(robust.transform, truth)[0] < 0.3 * pose_error(plain.transform, truth)[0]
    assert pose_error(robust.transform, truth)[0] < np.deg2rad(0.1)
    huber = register("plane", source, target, normals, loss=Huber(0.02))
    assert np.all(np.isfinite(np.asarray(huber.transform.parameters())))


def test_float32(pair):
    source, target, normals, truth = (
        jnp.asarray(a, jnp.float32) if not isinstance(a, SE3) else a for a in pair
    )
    result = register("plane", source, target, normals)
    assert result.transform.dtype == jnp.float32
    rotation, translation = pose_error(
        SE3(result.transform.parameters().astype(jnp.float64)), truth
    )
    assert rotation < 1e-4 and translation < 1e-4


def test_batched_pairs_of_different_sizes(pair):
    """Pairs of 250, 320 and 380 points, padded, in one vmapped call compiled once; each result
    equals the unbatched one."""
    pairs = [
        icp.synthetic_pair(n, rotation_deg=6.0, translation=0.05, seed=s)
        for n, s in ((250, 10), (320, 11), (380, 3))
    ]
    sources, source_mask = icp.pad_clouds([p[0] for p in pairs], ROWS)
    targets, target_mask = icp.pad_clouds([p[1] for p in pairs], ROWS)
    normals, _ = icp.pad_clouds([p[2] for p in pairs], ROWS)

    @jax.jit
    @jax.vmap
    def batch(s, sm, t, tm, n):
        return icp.point_to_plane(
            s,
            t,
            target_normals=n,
            source_mask=sm,
            target_mask=tm,
            max_correspondence_distance=RADIUS,
        )

    results = batch(sources, source_mask, targets, target_mask, normals)
    assert list(results.status_name) == ["CONVERGED"] * 3
    for k, (source, target, normal, truth) in enumerate(pairs):
        rotation, translation = pose_error(results.transform[k], truth)
        assert rotation < 1e-6 and translation < 1e-6
        single = register("plane", source, target, normal)
        np.testing.assert_allclose(
            np.asarray(results.transform[k].parameters()),
            np.asarray(single.transform.parameters()),
            atol=1e-9,
        )
        assert int(results.iterations[k]) == int(single.iterations)
    # Bad input inside vmap is a status, never an exception or a NaN transform.
    bad_sources = sources.at[0, 5].set(jnp.nan)
    far_targets = targets.at[1].add(100.0)
    bad = batch(bad_sources, source_mask, far_targets, target_mask, normals)
    assert list(bad.status_name) == ["NONFINITE", "DEGENERATE", "CONVERGED"]
    assert np.all(np.isfinite(np.asarray(bad.transform.parameters())))
    assert batch._cache_size() == 1  # one compilation for both batches


# ---- bad input ----------------------------------------------------------------------------------


def test_bad_shapes_raise(pair):
    source, target, normals, _ = pair
    with pytest.raises(ValueError, match="empty"):
        icp.point_to_plane(
            jnp.zeros((0, 3)), target, target_normals=normals, max_correspondence_distance=1.0
        )
    with pytest.raises(ValueError, match=r"shape \(n, 3\)"):
        icp.point_to_point(source[:, :2], target, max_correspondence_distance=1.0)
    with pytest.raises(ValueError, match="target_normals must have the shape of target"):
        icp.point_to_plane(
            source, target, target_normals=normals[:10], max_correspondence_distance=1.0
        )
    with pytest.raises(ValueError, match="source_mask"):
        icp.point_to_point(
            source, target, source_mask=jnp.ones(3, bool), max_correspondence_distance=1.0
        )
    with pytest.raises(TypeError, match="dtype"):
        icp.point_to_point(source.astype(jnp.float32), target, max_correspondence_distance=1.0)


def test_nonfinite_rows_raise_unless_masked(pair):
    source, target, normals, truth = pair
    broken = np.asarray(source).copy()
    broken[7] = np.nan
    with pytest.raises(icp.ICPError, match="not finite"):
        register("plane", broken, target, normals)
    init = SE3.exp(jnp.array([0.01, 0.0, 0.0, 0.0, 0.0, 0.02]))
    result = register("plane", broken, target, normals, throw=False, init=init)
    assert result.status_name == "NONFINITE"
    np.testing.assert_array_equal(
        np.asarray(result.transform.parameters()), np.asarray(init.parameters())
    )
    # The same row masked out is ignored.
    s, sm = padded(broken)
    t, tm = padded(target)
    result = icp.point_to_plane(
        s, t, target_normals=padded(normals)[0], source_mask=sm.at[7].set(False), target_mask=tm,
        max_correspondence_distance=RADIUS,
    )  # fmt: skip
    assert result.status_name == "CONVERGED"
    assert pose_error(result.transform, truth)[0] < 1e-6


def test_too_few_correspondences_is_degenerate(pair):
    source, target, normals, _ = pair
    far = np.asarray(target) + 50.0
    with pytest.raises(icp.ICPError, match="degenerate"):
        register("plane", source, far, normals)
    result = register("point", source, far, throw=False)
    assert result.status_name == "DEGENERATE"
    assert int(result.iterations) == 0
    assert np.all(np.isfinite(np.asarray(result.transform.parameters())))


def test_throw_under_jit_raises_when_the_program_runs(pair):
    """Under `jit`, `throw=True` raises the `ICPError` when the compiled program runs (a
    `JaxRuntimeError` carrying its message); under `vmap` a batch reports its statuses."""
    source, target, _, _ = pair
    s, sm = padded(source)
    t, tm = padded(target)

    @jax.jit
    def run(t, distance):
        return icp.point_to_point(
            s, t, source_mask=sm, target_mask=tm, max_correspondence_distance=distance
        )

    assert run(t, RADIUS).status_name == "CONVERGED"
    runtime_error = jax.errors.JaxRuntimeError
    with pytest.raises(
        runtime_error, match=r"ICPError: ICP is degenerate \(raised from inside jit"
    ):
        jax.block_until_ready(run(t + 50.0, RADIUS))
    with pytest.raises(runtime_error, match=r"ICPInputError: ICP input is not finite"):
        jax.block_until_ready(run(t.at[3].set(jnp.nan), RADIUS))
    with pytest.raises(runtime_error, match=r"ICPInputError: ICP parameter out of range"):
        jax.block_until_ready(run(t, -1.0))
    targets = jnp.stack([t, t + 50.0, t.at[3].set(jnp.nan), t])
    distances = jnp.array([RADIUS, RADIUS, RADIUS, -1.0])
    batch = jax.vmap(run)(targets, distances)
    assert list(batch.status_name) == ["CONVERGED", "DEGENERATE", "NONFINITE", "INVALID"]


# ---- real scans ---------------------------------------------------------------------------------

needs_data = pytest.mark.skipif(DATA_DIR is None, reason="set LIEAX_DATA_DIR to the shared data")


@needs_data
def test_pcl_bunny_pair():
    """PCL's tiny bunny pair (no ground truth): ICP from the identity converges and explains it
    (Open3D, same normals and distance: fitness 0.9917, inlier RMSE 4.76 mm)."""
    data = np.load(os.path.join(DATA_DIR, "clouds", "pcl_bun4_to_bun0", "pair.npz"))
    source, target = data["source"], data["target"]
    normals = icp.estimate_normals(jnp.asarray(target), k=10)
    result = register("plane", source, target, normals, max_correspondence_distance=0.02)
    assert result.status_name == "CONVERGED"
    assert float(result.fitness) > 0.99 and float(result.inlier_rmse) < 0.0048


@needs_data
def test_stanford_bunny_reaches_the_reference():
    """The 2 mm bunny pair from the identity: within 0.5 degrees and 2% of the extent of the
    reference, and (when Open3D is installed) within 0.01 degrees and 1e-4 of the extent of
    Open3D's registration_icp with the same normals and parameters."""
    data = np.load(os.path.join(DATA_DIR, "clouds", "bunny_045_to_000", "bunny_v0.002.npz"))
    source, target = jnp.asarray(data["source"]), jnp.asarray(data["target"])
    truth = SE3.from_matrix(jnp.asarray(data["T_target_source"]))
    extent = float(np.max(np.ptp(data["target"], axis=0)))
    normals = icp.estimate_normals(target, k=30, radius=0.006)
    result = icp.point_to_plane(
        source, target, target_normals=normals, max_correspondence_distance=0.01
    )
    rotation, translation = pose_error(result.transform, truth)
    assert result.status_name == "CONVERGED"
    assert np.rad2deg(rotation) < 0.5 and translation < 0.02 * extent
    o3d = pytest.importorskip("open3d")
    vectors = lambda p: o3d.utility.Vector3dVector(np.array(p, np.float64))
    target_cloud = o3d.geometry.PointCloud(vectors(target))
    target_cloud.normals = vectors(normals)
    reference = o3d.pipelines.registration.registration_icp(
        o3d.geometry.PointCloud(vectors(source)), target_cloud, 0.01, np.eye(4),
        o3d.pipelines.registration.TransformationEstimationPointToPlane(),
        o3d.pipelines.registration.ICPConvergenceCriteria(max_iteration=30),
    )  # fmt: skip
    open3d_pose = SE3.from_matrix(jnp.asarray(reference.transformation))
    rotation, translation = pose_error(result.transform, open3d_pose)
    assert np.rad2deg(rotation) < 0.01 and translation < 1e-4 * extent
    assert float(result.fitness) == pytest.approx(reference.fitness, abs=1e-9)
