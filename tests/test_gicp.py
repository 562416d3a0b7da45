"""Tests of lieax.icp's generalized ICP and multi-scale registration: covariances against a NumPy
reference, the normal equations against autodiff of the GICP cost, recovery of known motions
(float64, float32, robust loss, vmap over pairs), bad input, coarse-to-fine registration, and the
Stanford bunny against small_gicp when `LIEAX_DATA_DIR` is set.

Compilation dominates the cost, so every synthetic cloud is padded to `ROWS` rows (masked): the
GICP loop compiles once per dtype (and once for the `vmap`ped batch).
"""

import os

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from lieax import SE3, icp
from lieax.icp import _covariances, _gicp, _host_kdtree, _normals
from lieax.lstsq import Cauchy

ROWS = 400
RADIUS = 0.4  # max_correspondence_distance on the synthetic scene (about 2 m across)
DATA_DIR = os.environ.get("LIEAX_DATA_DIR")


def padded(points, rows=ROWS):
    points = np.asarray(points)
    out = np.zeros((rows,) + points.shape[1:], points.dtype)
    out[: len(points)] = points
    return jnp.asarray(out), jnp.asarray(np.arange(rows) < len(points))


def pose_error(estimate: SE3, truth: SE3):
    """(rotation error in radians, translation error) between two poses."""
    estimate = SE3(estimate.parameters().astype(truth.dtype))  # a float32 estimate, float64 truth
    xi = np.asarray(truth.inverse().compose(estimate).log())
    translation = np.asarray(estimate.translation() - truth.translation())
    return float(np.linalg.norm(xi[3:])), float(np.linalg.norm(translation))


def register(source, target, **kwargs):
    """`icp.gicp` on the clouds padded to `ROWS`, from an explicit identity `init` (one compiled
    loop per dtype, shared with the tests that start elsewhere)."""
    s, sm = padded(source)
    t, tm = padded(target)
    options = {"max_correspondence_distance": RADIUS, "source_mask": sm, "target_mask": tm}
    return icp.gicp(s, t, **{"init": SE3.identity(), **options, **kwargs})


def reference_covariances(points, k, epsilon=1e-3):
    """small_gicp's rule in NumPy: the k nearest (SciPy's cKDTree), eigh, diag(eps, 1, 1)."""
    from scipy.spatial import cKDTree

    _, neighbours = cKDTree(points).query(points, k=k)
    out = []
    for members in points[neighbours]:
        centred = members - members.mean(axis=0)
        _, vectors = np.linalg.eigh(centred.T @ centred / k)
        out.append(vectors @ np.diag([epsilon, 1.0, 1.0]) @ vectors.T)
    return np.array(out)


@pytest.fixture(scope="module")
def pair():
    return icp.synthetic_pair(380, rotation_deg=8.0, translation=0.08, seed=3)


# ---- covariances --------------------------------------------------------------------------------


@pytest.mark.parametrize("search", ["kdtree", "kdtree scipy", "graph"])
def test_covariances_match_a_numpy_reference(search, monkeypatch):
    """The covariances against small_gicp's rule in NumPy; `"kdtree"` is the native tree where
    the library is built, `"kdtree scipy"` the host tree forced to SciPy's (as without the native
    library and pykdtree), the same covariances."""
    if search == "kdtree scipy":
        monkeypatch.setattr(_host_kdtree, "default_library", lambda dtype=None: "scipy")
        search = "kdtree"
    points = np.asarray(icp.synthetic_scene(390, noise=0.002, seed=4)[0])
    cloud, mask = padded(points)
    estimated = np.asarray(icp.estimate_covariances(cloud, k=20, mask=mask, search=search))
    reference = reference_covariances(points, 20)
    gap = np.max(np.abs(estimated[: len(points)] - reference), axis=(1, 2))
    # The neighbour graph is exact within its coverage radius: nearly every neighbourhood is the
    # k-d tree's; the rest differ by a far neighbour swapped for an equally far one.
    assert np.mean(gap < 1e-8) > (0.999 if search == "kdtree" else 0.97)
    assert np.median(gap) < 1e-10
    np.testing.assert_array_equal(estimated[len(points) :], np.broadcast_to(np.eye(3), (10, 3, 3)))
    if search == "kdtree":  # the host tree under jit too (a host callback), the same result
        traced = jax.jit(lambda c, m: icp.estimate_covariances(c, k=20, mask=m, search=search))
        np.testing.assert_array_equal(traced(cloud, mask), estimated)
    eigenvalues = np.linalg.eigvalsh(estimated[: len(points)])
    np.testing.assert_allclose(eigenvalues, np.broadcast_to([1e-3, 1.0, 1.0], eigenvalues.shape))


def test_covariances_equal_small_gicps():
    """small_gicp's own `estimate_covariances` (k = 20, its regularization), where installed."""
    small_gicp = pytest.importorskip("small_gicp")
    points = np.asarray(icp.synthetic_scene(390, noise=0.002, seed=4)[0])
    cloud = small_gicp.PointCloud(points)
    small_gicp.estimate_covariances(cloud, num_neighbors=20)
    theirs = np.asarray(cloud.covs())[:, :3, :3]
    cloud_rows, mask = padded(points)
    ours = np.asarray(icp.estimate_covariances(cloud_rows, k=20, mask=mask, search="kdtree"))
    np.testing.assert_allclose(ours[: len(points)], theirs, atol=1e-10)


@pytest.mark.parametrize("search", ["kdtree", "graph"])
def test_covariances_of_small_neighbourhoods_are_the_identity(search):
    points = jnp.asarray(np.random.default_rng(0).normal(size=(6, 3)))
    mask = jnp.asarray([True] * 4 + [False] * 2)  # 4 valid points: fewer than 5 neighbours
    np.testing.assert_array_equal(
        icp.estimate_covariances(points, k=5, mask=mask, search=search),
        np.broadcast_to(np.eye(3), (6, 3, 3)),
    )
    with pytest.raises(ValueError, match="k must be an int of at least 5"):
        icp.estimate_covariances(points, k=4)
    with pytest.raises(ValueError, match="search must be 'auto', 'graph' or 'kdtree'"):
        icp.estimate_covariances(points, search="grid")


def test_host_covariances_differentiate_and_batch_as_the_jax_path():
    """The k-d tree path sums the neighbourhoods on the host: its derivatives (neighbourhoods
    held fixed), `vmap` and float32 results are those of the JAX sums over the same
    neighbourhoods (`_covariances_of_neighbours`)."""
    points = np.asarray(icp.synthetic_scene(390, noise=0.002, seed=4)[0])
    cloud, mask = padded(points)
    found = _normals.neighbourhoods(cloud, mask, 20, search="kdtree")

    def jax_path(c):
        return _covariances._covariances_of_neighbours(c, mask, found)

    def host_path(c):
        return icp.estimate_covariances(c, k=20, mask=mask, search="kdtree")

    direction = jnp.asarray(np.random.default_rng(1).normal(size=cloud.shape))
    value, tangent = jax.jvp(host_path, (cloud,), (direction,))
    expected_value, expected_tangent = jax.jvp(jax_path, (cloud,), (direction,))
    np.testing.assert_allclose(value, expected_value, atol=1e-10)
    np.testing.assert_allclose(tangent, expected_tangent, atol=1e-8)
    stacked = jnp.stack([cloud, cloud[::-1]])
    batched = jax.vmap(lambda c, m: icp.estimate_covariances(c, k=20, mask=m))(
        stacked, jnp.stack([mask, mask[::-1]])
    )
    np.testing.assert_allclose(batched[0], value, atol=1e-12)
    np.testing.assert_allclose(batched[1], value[::-1], atol=1e-12)
    single = icp.estimate_covariances(cloud.astype(jnp.float32), k=20, mask=mask)
    assert single.dtype == jnp.float32
    np.testing.assert_allclose(single, value, atol=1e-4)


# ---- the normal equations -----------------------------------------------------------------------


def random_covariances(rng, n):
    a = rng.normal(size=(n, 3, 3))
    return jnp.asarray(a @ np.swapaxes(a, 1, 2) + 0.1 * np.eye(3))


@jax.jit
def autodiff_normal_equations(params, source, matched, m, weights):
    r"""$J^\top W M J$, $\tfrac12 \nabla f$ and $\tfrac12 \nabla^2 f$ of the GICP cost $f$ with $M$
    fixed, $J$ by autodiff of the residuals through `rplus` at 0 (one compile for every pose)."""
    pose = SE3(params)

    def residuals(xi):
        return pose.rplus(xi) @ source - matched

    def cost(xi):
        r = residuals(xi)
        return jnp.sum(weights * jnp.einsum("ni,nij,nj->n", r, m, r))

    zero = jnp.zeros(6, params.dtype)
    jac = jax.jacfwd(residuals)(zero)  # (n, 3, 6)
    hessian = jnp.einsum("n,nai,nab,nbj->ij", weights, jac, m, jac)
    return hessian, 0.5 * jax.grad(cost)(zero), 0.5 * jax.hessian(cost)(zero)


POSES = {  # rotation vectors and translations: the identity, near it, near pi, random
    "identity": (np.zeros(3), np.zeros(3)),
    "1e-9 from the identity": (1e-9 * np.array([0.6, -0.8, 0.0]), np.zeros(3)),
    "1e-4 rad": (1e-4 * np.array([0.0, 0.6, 0.8]), np.array([0.1, 0.0, -0.2])),
    "pure translation": (np.zeros(3), np.array([0.3, -1.2, 0.5])),
    "pi - 1e-4": ((np.pi - 1e-4) * np.array([0.48, 0.6, 0.64]), np.array([0.2, 0.1, 0.0])),
    "pi - 1e-6": ((np.pi - 1e-6) * np.array([0.0, 0.6, -0.8]), np.array([-0.5, 0.0, 0.3])),
    "random": (np.array([0.4, -1.1, 0.7]), np.array([1.0, 2.0, -0.5])),
}


@pytest.mark.parametrize("at_the_solution", [False, True])
def test_normal_equations_match_autodiff_of_the_cost(at_the_solution):
    r"""$g = \tfrac12 \nabla f$ and $H = J^\top M J$ with $J$ by autodiff of the residuals
    through `rplus`, at the identity, near it, near $\pi$ and at random poses; at a
    zero-residual pose $H$ is also the Hessian $\tfrac12 \nabla^2 f$."""
    rng = np.random.default_rng(1)
    n = 50
    source = jnp.asarray(rng.normal(size=(n, 3)))
    noise = 0.0 if at_the_solution else jnp.asarray(rng.normal(size=(n, 3)))
    cs, cd = random_covariances(rng, n), random_covariances(rng, n)
    weights = jnp.asarray(rng.uniform(0.2, 1.0, size=n))
    normal_equations = jax.jit(_gicp.gicp_normal_equations)
    for name, (rotation_vector, translation) in POSES.items():
        rotation = SE3.exp(jnp.asarray(np.concatenate([np.zeros(3), rotation_vector])))
        pose = SE3.from_translation(jnp.asarray(translation)) @ rotation
        matched = pose @ source + noise
        hessian, gradient, costs = normal_equations(
            pose.parameters(), source, matched, cs, cd, weights
        )
        r_matrix = np.asarray(pose.rotation().as_matrix())
        m = np.linalg.inv(np.asarray(cd) + r_matrix @ np.asarray(cs) @ r_matrix.T)  # at pose
        expected_h, expected_g, cost_hessian = autodiff_normal_equations(
            pose.parameters(), source, matched, jnp.asarray(m), weights
        )
        np.testing.assert_allclose(hessian, expected_h, rtol=1e-10, atol=1e-10, err_msg=name)
        np.testing.assert_allclose(gradient, expected_g, atol=1e-10, err_msg=name)
        r = np.asarray(pose @ source - matched)
        np.testing.assert_allclose(
            costs, np.einsum("ni,nij,nj->n", r, m, r), rtol=1e-10, atol=1e-20, err_msg=name
        )
        if at_the_solution:
            np.testing.assert_allclose(gradient, 0.0, atol=1e-10, err_msg=name)
            np.testing.assert_allclose(hessian, cost_hessian, rtol=1e-8, atol=1e-8, err_msg=name)


# ---- registration -------------------------------------------------------------------------------


@pytest.mark.parametrize("dtype", [jnp.float64, jnp.float32])
def test_gicp_recovers_a_known_motion(pair, dtype):
    source, target, _, truth = pair
    result = register(source.astype(dtype), target.astype(dtype))
    assert result.status_name == "CONVERGED"
    assert result.transform.parameters().dtype == dtype
    rotation, translation = pose_error(result.transform, truth)
    tolerance = 1e-9 if dtype == jnp.float64 else 2e-4
    assert rotation < tolerance and translation < tolerance
    assert float(result.fitness) == pytest.approx(1.0)
    assert float(result.inlier_rmse) < tolerance
    matched = np.asarray(result.correspondences)
    np.testing.assert_array_equal(matched[:380], np.arange(380))  # the same samples, moved
    assert np.all(matched[380:] == -1)


def test_gicp_stops_after_the_first_step_below_its_tolerances(pair):
    """small_gicp's rule alone (Open3D's tolerances 0): the run stops after the first update whose
    rotation and translation, in the clouds' own frames, are both below their tolerances, at that
    update's pose. The clouds sit metres from the origin, where the translation of a step differs
    from that of the loop's centred frame. Single updates (huge tolerances: stop after one)
    chained from the start give the run's poses, so its steps."""
    source, target, _, _ = pair
    source_offset, target_offset = np.array([3.0, -2.0, 1.5]), np.array([-1.0, 4.0, 2.0])
    s, sm = padded(np.asarray(source) + source_offset)
    t, tm = padded(np.asarray(target) + target_offset)
    cs, ct = icp.estimate_covariances(s, mask=sm), icp.estimate_covariances(t, mask=tm)
    start = SE3.from_translation(jnp.asarray(target_offset - source_offset))

    def run(init, **tolerances):
        return icp.gicp(
            s, t, source_mask=sm, target_mask=tm, source_covariances=cs, target_covariances=ct,
            max_correspondence_distance=RADIUS, init=init, relative_fitness=0.0,
            relative_rmse=0.0, **tolerances,
        )  # fmt: skip

    poses = [start]
    for _ in range(6):
        single = run(poses[-1], rotation_epsilon=1e9, translation_epsilon=1e9)
        assert single.status_name == "CONVERGED" and int(single.iterations) == 1
        poses.append(single.transform)
    steps = [before.inverse() @ after for before, after in zip(poses, poses[1:])]
    rotations = np.array([np.asarray(step.rotation().as_matrix()) for step in steps])
    translations = np.array([np.asarray(step.translation()) for step in steps])
    sizes = {
        "rotation": np.array([np.linalg.norm(np.asarray(step.rotation().log())) for step in steps]),
        "translation": np.linalg.norm(translations, axis=1),
    }

    def check(result, first_small):
        assert result.status_name == "CONVERGED"
        assert int(result.iterations) == first_small + 1
        np.testing.assert_allclose(
            result.transform.parameters(), poses[first_small + 1].parameters(), atol=1e-12
        )

    for part, size in sizes.items():  # a tolerance between the 3rd update's size and the 4th's
        assert size[3] < np.min(size[:3]) / 10
        tolerances = {"rotation_epsilon": 1e9, "translation_epsilon": 1e9}
        tolerances[f"{part}_epsilon"] = np.sqrt(size[3] * np.min(size[:3]))
        check(run(start, **tolerances), 3)
    # The translation is the clouds' own: about the source's centroid (the loop's frame) the
    # first update moves by another amount, and a tolerance between the two tells them apart.
    centroid = np.mean(np.asarray(source), axis=0) + source_offset
    about_centroid = np.linalg.norm(translations + rotations @ centroid - centroid, axis=1)
    tolerance = np.sqrt(sizes["translation"][0] * about_centroid[0])
    first_small = int(np.argmax(sizes["translation"] < tolerance))
    assert first_small != int(np.argmax(about_centroid < tolerance))
    check(run(start, rotation_epsilon=1e9, translation_epsilon=tolerance), first_small)
    # The defaults: 0.1° and 1e-3 max_correspondence_distance.
    small = (sizes["rotation"] < np.deg2rad(0.1)) & (sizes["translation"] < 1e-3 * RADIUS)
    assert np.any(small) and not small[0]
    check(run(start), int(np.argmax(small)))


def test_gicp_with_a_robust_loss_ignores_outliers(pair):
    """A fifth of the source is moved off the surfaces by up to 0.2: least squares is pulled
    away, Cauchy's IRLS weights drop those pairs."""
    source, target, _, truth = pair
    rng = np.random.default_rng(7)
    broken = np.array(source)
    rows = rng.choice(len(broken), size=len(broken) // 5, replace=False)
    broken[rows] += rng.uniform(-0.2, 0.2, size=(len(rows), 3))
    source_covariances = icp.estimate_covariances(source)  # of the clean cloud
    covariances = padded(source_covariances)[0]
    plain = register(broken, target, source_covariances=covariances)
    robust = register(broken, target, source_covariances=covariances, loss=Cauchy(1e-3))
    plain_error = pose_error(plain.transform, truth)
    robust_error = pose_error(robust.transform, truth)
    assert robust_error[0] < 2e-3 and robust_error[1] < 2e-3
    assert plain_error[0] > 5 * robust_error[0]


def test_gicp_under_vmap_over_padded_pairs():
    pairs = [icp.synthetic_pair(n, rotation_deg=8.0, seed=seed) for n, seed in ((300, 1), (380, 2))]
    sources, source_mask = icp.pad_clouds([p[0] for p in pairs], ROWS)
    targets, target_mask = icp.pad_clouds([p[1] for p in pairs], ROWS)
    far = sources + 100.0  # a third pair with no overlap: DEGENERATE, no exception under vmap
    sources = jnp.concatenate([sources, far[:1]])
    source_mask = jnp.concatenate([source_mask, source_mask[:1]])
    targets = jnp.concatenate([targets, targets[:1]])
    target_mask = jnp.concatenate([target_mask, target_mask[:1]])

    def run(s, sm, t, tm):
        return icp.gicp(s, t, source_mask=sm, target_mask=tm, max_correspondence_distance=RADIUS)

    results = jax.jit(jax.vmap(run))(sources, source_mask, targets, target_mask)
    assert list(results.status_name) == ["CONVERGED", "CONVERGED", "DEGENERATE"]
    for i, (_, _, _, truth) in enumerate(pairs):
        pose = SE3._wrap(results.transform.parameters()[i])
        assert max(pose_error(pose, truth)) < 1e-8


# ---- bad input ----------------------------------------------------------------------------------


def test_gicp_bad_input_is_named(pair):
    source, target, _, _ = pair
    with pytest.raises(ValueError, match=r"source_covariances must have shape \(380, 3, 3\)"):
        icp.gicp(source, target, source_covariances=jnp.zeros((380, 3)),
                 max_correspondence_distance=RADIUS)  # fmt: skip
    with pytest.raises(TypeError, match="target_covariances must have the points' dtype"):
        icp.gicp(source, target, target_covariances=jnp.zeros((380, 3, 3), jnp.float32),
                 max_correspondence_distance=RADIUS)  # fmt: skip
    with pytest.raises(TypeError, match="target_covariances must have a floating dtype"):
        icp.gicp(source, target, target_covariances=np.zeros((380, 3, 3), int),
                 max_correspondence_distance=RADIUS)  # fmt: skip
    with pytest.raises(ValueError, match="source must have shape"):
        icp.gicp(source[:, :2], target, max_correspondence_distance=RADIUS)
    with pytest.raises(ValueError, match="max_correspondence_distance must be positive"):
        icp.gicp(source, target, max_correspondence_distance=0.0)
    with pytest.raises(ValueError, match="rotation_epsilon must be non-negative"):
        icp.gicp(source, target, max_correspondence_distance=RADIUS, rotation_epsilon=-1.0)
    with pytest.raises(ValueError, match="translation_epsilon must be non-negative"):
        icp.gicp(source, target, max_correspondence_distance=RADIUS, translation_epsilon=np.nan)


def test_gicp_nonfinite_and_degenerate_input(pair):
    source, target, _, _ = pair
    covariances = np.array(padded(icp.estimate_covariances(target))[0])
    covariances[5, 0, 0] = np.nan
    with pytest.raises(icp.ICPError, match="not finite"):
        register(source, target, target_covariances=jnp.asarray(covariances))
    result = register(source, target, target_covariances=jnp.asarray(covariances), throw=False)
    assert result.status_name == "NONFINITE"
    # A NaN in a masked-out (padding) row is ignored.
    covariances[5, 0, 0] = 1.0
    covariances[ROWS - 1, 0, 0] = np.nan
    assert register(source, target, target_covariances=jnp.asarray(covariances)).converged
    with pytest.raises(icp.ICPError, match="degenerate"):
        register(source, target + 100.0)


# ---- multi-scale --------------------------------------------------------------------------------


def test_multi_scale_converges_where_the_finest_level_alone_does_not():
    source, target, _, truth = icp.synthetic_pair(
        380, rotation_deg=45.0, translation=0.4, noise=0.002, same_samples=False, seed=3
    )
    single = register(source, target, max_correspondence_distance=0.1, throw=False)
    assert pose_error(single.transform, truth)[0] > 0.1  # a wrong local minimum
    s, sm = padded(source)
    t, tm = padded(target)
    result, levels = icp.multi_scale(
        s, t, source_mask=sm, target_mask=tm, voxel_sizes=(0.3, None),
        max_correspondence_distances=(1.0, 0.1), method="gicp", return_levels=True,
    )  # fmt: skip
    assert len(levels) == 2 and levels[1] is result
    coarse = levels[0].correspondences
    assert coarse.shape[0] < ROWS and np.sum(coarse >= 0) > 50  # ran on voxel centroids
    assert result.status_name == "CONVERGED"
    rotation, translation = pose_error(result.transform, truth)
    assert rotation < 0.01 and translation < 0.01  # the noise level (2 mm, independent samples)


def test_multi_scale_bad_input():
    points = jnp.zeros((10, 3))
    with pytest.raises(ValueError, match="method must be one of"):
        icp.multi_scale(points, points, voxel_sizes=(1.0,), max_correspondence_distances=(1.0,),
                        method="plane")  # fmt: skip
    with pytest.raises(ValueError, match="one entry per level"):
        icp.multi_scale(points, points, voxel_sizes=(1.0, 0.5), max_correspondence_distances=(1.0,))
    with pytest.raises(ValueError, match="at least one level"):
        icp.multi_scale(points, points, voxel_sizes=(), max_correspondence_distances=())


# ---- real data ----------------------------------------------------------------------------------


@pytest.mark.slow
@pytest.mark.skipif(DATA_DIR is None, reason="LIEAX_DATA_DIR is not set")
def test_gicp_on_the_bunny_matches_small_gicp():
    """The Stanford bunny at 2 mm, 1 cm distance, covariances from 20 neighbours, from the
    identity: no worse than small_gicp (0.0754°, 0.106 mm from `bun.conf` here) against the
    reference, and within 0.01° / 0.05 mm of small_gicp's pose."""
    small_gicp = pytest.importorskip("small_gicp")
    data = np.load(os.path.join(DATA_DIR, "clouds", "bunny_045_to_000", "bunny_v0.002.npz"))
    source, target = data["source"], data["target"]
    truth = SE3.from_matrix(jnp.asarray(data["T_target_source"]))
    source_cloud, target_cloud = small_gicp.PointCloud(source), small_gicp.PointCloud(target)
    tree = small_gicp.KdTree(target_cloud)
    small_gicp.estimate_covariances(source_cloud, num_neighbors=20)
    small_gicp.estimate_covariances(target_cloud, tree, num_neighbors=20)
    peer = small_gicp.align(
        target_cloud, source_cloud, tree, registration_type="GICP",
        max_correspondence_distance=0.01, max_iterations=30,
    )  # fmt: skip
    assert peer.converged
    peer_pose = SE3.from_matrix(jnp.asarray(peer.T_target_source))

    result = icp.gicp(jnp.asarray(source), jnp.asarray(target), max_correspondence_distance=0.01)
    assert result.status_name == "CONVERGED"
    rotation, translation = pose_error(result.transform, truth)
    peer_rotation, peer_translation = pose_error(peer_pose, truth)
    assert rotation < peer_rotation + np.deg2rad(0.002)
    assert translation < peer_translation + 2e-6
    gap = pose_error(result.transform, peer_pose)
    assert gap[0] < np.deg2rad(0.01) and gap[1] < 5e-5


def test_derivatives_through_gicp_are_a_clear_error(pair):
    source, target, _, _ = pair
    s, sm = padded(source)
    t, tm = padded(target)

    def rotation_angle(shift):
        result = icp.gicp(
            s + shift, t, source_mask=sm, target_mask=tm, max_correspondence_distance=RADIUS
        )
        return jnp.sum(result.transform.log()[3:] ** 2)

    with pytest.raises(NotImplementedError, match="derivatives through ICP of kind 'gicp'"):
        jax.grad(rotation_angle)(jnp.zeros(3))
