"""The nearest-neighbour backends (`lieax.icp._search`): each against SciPy's exact cKDTree, inside
ICP against each other, under `vmap`, and their errors."""

import importlib.util

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from scipy.spatial import cKDTree

from lieax import _native, icp
from lieax.icp import _grid, _host_kdtree, _search

BACKENDS = ("grid", "kdtree", "brute")


@jax.jit
def _nearest(index, queries, radius, mask):
    return _search.nearest(index, queries, radius=radius, mask=mask)


def _dense_cloud(rng):
    """Cells of the radius holding hundreds of points each, and sparse points around them."""
    dense = rng.uniform(0.0, 0.25, (2500, 3))
    sparse = rng.uniform(-1.0, 1.0, (500, 3))
    target = np.concatenate([dense, sparse])
    queries = np.concatenate([rng.uniform(-0.1, 0.35, (600, 3)), rng.uniform(-1.2, 1.2, (300, 3))])
    return target, queries, 0.1


def _ring_cloud(rng):
    """A LiDAR-like scan: rings on the ground around the sensor plus a wall, 1 m radius."""
    rings = []
    for rho in np.geomspace(3.0, 40.0, 12):
        angle = rng.uniform(0, 2 * np.pi, 200)
        rings.append(np.stack([rho * np.cos(angle), rho * np.sin(angle), -1.7 + 0 * angle], 1))
    wall = np.stack([rng.uniform(-20, 20, 600), np.full(600, 15.0), rng.uniform(-1.7, 3, 600)], 1)
    target = np.concatenate(rings + [wall])
    queries = target[rng.choice(len(target), 900, replace=False)] + rng.normal(0, 0.4, (900, 3))
    return target, queries, 1.0


def _far_queries(rng):
    """No query has a target point within the radius."""
    target = rng.uniform(-1, 1, (3000, 3))
    return target, rng.uniform(5, 6, (900, 3)) * rng.choice([-1, 1], (900, 3)), 0.5


# Every cloud has 3000 target points and 900 queries: one compilation per backend and dtype.
CLOUDS = {"dense": _dense_cloud, "rings": _ring_cloud, "far": _far_queries}


def _check_against_kdtree(result, target, target_mask, queries, query_mask, radius, exact_only):
    kept = np.flatnonzero(target_mask)
    reference, _ = cKDTree(target[kept]).query(queries, 1)
    distance, index = np.asarray(result.distance), np.asarray(result.index)
    within = (reference <= radius) & query_mask
    assert within.any() or not np.any(reference <= radius)
    tol = 1e-5 * max(1.0, np.abs(target).max()) if target.dtype == np.float32 else 1e-12
    np.testing.assert_allclose(distance[within], reference[within], rtol=0, atol=tol)
    # Indices equal up to ties: the reported point is valid and at the reference distance.
    assert np.all(target_mask[index[within]])
    gap = np.linalg.norm(target[index[within]] - queries[within], axis=1)
    np.testing.assert_allclose(gap, reference[within], rtol=0, atol=tol)
    beyond = (reference > radius * (1 + 1e-5)) & query_mask
    assert np.all(distance[beyond] > radius)
    if exact_only:
        assert np.all(np.isinf(distance[beyond])) and np.all(index[beyond] == -1)


# Every backend on every cloud in float64 and float32; "kdtree scipy": the host tree forced to
# SciPy's (the default without pykdtree, the bench extra).
CASES = [
    (search, cloud, dtype)
    for search in BACKENDS + ("kdtree scipy",)
    for cloud in sorted(CLOUDS)
    for dtype in (np.float64, np.float32)
]


@pytest.mark.parametrize("search, cloud, dtype", CASES)
def test_nearest_equals_ckdtree_within_radius(search, cloud, dtype):
    rng = np.random.default_rng(sorted(CLOUDS).index(cloud))
    target, queries, radius = (a if np.isscalar(a) else a.astype(dtype) for a in CLOUDS[cloud](rng))
    target_mask = rng.uniform(size=len(target)) > 0.2
    query_mask = rng.uniform(size=len(queries)) > 0.1
    options = {"library": "scipy"} if search == "kdtree scipy" else {}
    search = search.split()[0]
    index = _search.build_index(target, target_mask, search=search, max_distance=radius, **options)
    result = _nearest(index, queries, radius, query_mask)
    _check_against_kdtree(result, target, target_mask, queries, query_mask, radius, True)


@pytest.mark.parametrize("capacity", [16, 2**22])
def test_grid_is_exact_with_colliding_buckets_and_wide_tables(capacity):
    """16 buckets: each mixes many cells; 2**22: keys too wide to pack (a key-value sort)."""
    rng = np.random.default_rng(3)
    target, queries, radius = _dense_cloud(rng)
    index = _grid.build_grid(target, cell_size=radius, capacity=capacity)
    assert index.capacity == capacity
    result = _nearest(index, queries, radius, np.ones(len(queries), bool))
    ones = np.ones(len(target), bool)
    _check_against_kdtree(result, target, ones, queries, np.ones(len(queries), bool), radius, True)


@pytest.mark.parametrize("library", ["native", "host"])
def test_kdtree_warm_start_keeps_only_provably_nearest_matches(library):
    """Earlier matches kept by the spacing test (right ones, wrong ones, random ones) change
    nothing: the result is still the exact nearest point within the radius (the native tree
    ignores them). The host tree computes the spacing at the first such query, not at the
    build; both give the spacing."""
    if library == "native" and not _native.available():
        pytest.skip("the native library is not built")
    rng = np.random.default_rng(5)
    target, queries, radius = _ring_cloud(rng)
    library = _host_kdtree.host_library() if library == "host" else library
    index = _search.build_index(target, search="kdtree", library=library)
    exact = _search.match(index, queries, radius)
    reference, _ = cKDTree(target).query(queries, 1)
    within = reference <= radius
    if library != "native":
        assert _host_kdtree._entry(index.tree)[4] is None  # the spacing waits for `previous`
    match = jax.jit(lambda q, p: _search.match(index, q, radius, previous=p))
    for previous in (exact[0], rng.integers(0, len(target), len(queries)), exact[0][::-1]):
        _, d2 = match(queries, jnp.asarray(previous, jnp.int32))
        np.testing.assert_allclose(np.sqrt(d2[within]), reference[within], rtol=0, atol=1e-12)
        assert np.all(np.isinf(d2[~within]))
    spacing, _ = cKDTree(target).query(target, 2)
    np.testing.assert_allclose(
        _host_kdtree.kdtree_spacing(index), spacing[:, 1], rtol=0, atol=1e-12
    )


def test_normals_from_the_host_tree_and_the_graph_agree():
    """`estimate_normals` with its neighbourhoods from the host k-d tree (the CPU default) and
    from the graph: the same normals on a dense sphere (up to the graph's rare approximate
    neighbourhoods), both within 10 degrees of the true normals (the irregular sampling tilts a
    few by up to 8), masked rows zero. The host tree is pykdtree's where it is installed (the
    bench extra), else SciPy's."""
    rng = np.random.default_rng(3)
    points = rng.normal(size=(2000, 3))
    points /= np.linalg.norm(points, axis=1, keepdims=True)
    mask = np.arange(2000) % 10 != 0
    normals = {
        search: np.asarray(icp.estimate_normals(points, k=12, mask=mask, search=search))
        for search in ("kdtree", "graph")
    }
    same = np.sum(normals["kdtree"] * normals["graph"], axis=1)
    assert np.mean(same[mask] > 1 - 1e-9) > 0.98
    for found in normals.values():
        assert np.all(found[~mask] == 0)
        # viewpoint at the origin: the normals face inward
        assert np.all(np.sum(found[mask] * -points[mask], axis=1) > np.cos(np.radians(10)))


@pytest.mark.parametrize("library", ["scipy", "pykdtree", "native"])
def test_host_neighbourhoods_survive_repeated_points(library):
    """The k-d tree of the normals, inside XLA's callback (flush-to-zero and denormals-are-zero
    set) or custom call, on a cloud with more repeats of one point than a leaf holds: SciPy's
    default `cKDTree` build segfaults there (`lieax.icp._normals`), the unbalanced one, pykdtree
    and the native tree give the exact `k` nearest distances (NumPy's brute force)."""
    if library == "pykdtree" and importlib.util.find_spec("pykdtree") is None:
        pytest.skip("pykdtree is not installed (the bench extra)")
    if library == "native" and not _native.available():
        pytest.skip("the native library is not built")
    from lieax.icp import _normals

    rng = np.random.default_rng(0)
    points = np.concatenate([rng.normal(size=(200, 3)), np.zeros((40, 3))])
    mask = np.arange(len(points)) % 7 != 3
    found = np.asarray(
        _normals._kdtree_neighbourhoods_call(
            jnp.asarray(points), jnp.asarray(mask), k=12, library=library
        )
    )
    valid = points[mask]
    gaps = np.linalg.norm(valid[:, None] - valid[None], axis=-1)
    expected = np.sort(gaps, axis=1)[:, :12]
    got = np.linalg.norm(points[found[mask]] - valid[:, None], axis=-1)
    np.testing.assert_allclose(np.sort(got, axis=1), expected, rtol=0, atol=1e-12)
    assert np.all(found[~mask] == -1) and np.all(mask[found[mask]])


@pytest.mark.parametrize("dtype", [np.float64, np.float32])
def test_kdtree_tracking_stays_exact_and_keeps_queries_that_barely_move(dtype):
    """`track_in_kdtree` over a sequence of large, then shrinking moves (ICP's iterations): every
    answer is the exact nearest point within the radius (SciPy's), masked queries get none, the
    large moves ask the host for the nearest point only (their matches' allowances are 0), and
    once the moves are small most queries are answered without the host."""
    rng = np.random.default_rng(7)
    target = rng.uniform(-1, 1, (3000, 3)).astype(dtype)
    queries = rng.uniform(-1.2, 1.2, (900, 3)).astype(dtype)
    mask = rng.uniform(size=900) > 0.1
    radius = 0.08
    index = _search.build_index(jnp.asarray(target), search="kdtree")
    track = jax.jit(
        lambda q, w: _host_kdtree.track_in_kdtree(index, q, radius, w, mask=jnp.asarray(mask))
    )
    warm = _host_kdtree.cold_start(len(queries), dtype)
    tree = cKDTree(target.astype(np.float64))
    nearest_only = []
    for step in range(10):
        slot, d2, new = track(jnp.asarray(queries), warm)
        sent = np.any(np.asarray(new.queries) != np.asarray(warm.queries), axis=1)
        matched = sent & (np.asarray(new.slot) >= 0)
        nearest_only.append(bool(np.all(np.asarray(new.allowance)[matched] == 0)))
        distance, nearest = tree.query(queries.astype(np.float64))
        within = (distance <= radius) & mask
        assert np.array_equal(np.isfinite(d2), within)
        tolerance = 1e-12 if dtype == np.float64 else 1e-6
        np.testing.assert_allclose(np.sqrt(d2[within]), distance[within], atol=tolerance)
        kept = np.all(np.asarray(new.queries) != queries, axis=1)  # (not re-sent: old positions)
        warm = new
        scale = 0.1 if step < 3 else 0.02 / (step - 2) ** 2
        queries = queries + rng.normal(scale=scale, size=queries.shape).astype(dtype)
    # (the first call, from the cold start, asks for two; the moves of 0.1 then for one)
    assert nearest_only[:4] == [False, True, True, True] and not any(nearest_only[5:])
    assert np.mean(kept[mask]) > 0.8


@pytest.mark.parametrize("search", BACKENDS)
def test_distance_derivatives_forward_and_reverse(search):
    """d|q - p|/dq = (q - p)/|q - p| at the match p, against central differences (the match is
    locally constant), in forward and reverse mode."""
    rng = np.random.default_rng(6)
    target, queries = rng.uniform(-1, 1, (300, 3)), rng.uniform(-0.8, 0.8, (40, 3))
    index = _search.build_index(target, search=search, max_distance=0.6)

    def total(q):
        distance = _search.nearest(index, q, radius=0.6).distance
        return jnp.sum(jnp.where(jnp.isfinite(distance), distance, 0.0))

    # jitted (a program each, where op-by-op evaluation compiles one per operation)
    reverse = jax.jit(jax.grad(total))(jnp.asarray(queries))
    direction = rng.normal(size=queries.shape)
    forward_mode = jax.jit(lambda q, d: jax.jvp(total, (q,), (d,))[1])
    forward = forward_mode(jnp.asarray(queries), jnp.asarray(direction))
    h, total_jitted = 1e-6, jax.jit(total)
    central = (total_jitted(queries + h * direction) - total_jitted(queries - h * direction)) / (
        2 * h
    )
    assert np.all(np.isfinite(reverse))
    np.testing.assert_allclose(forward, central, rtol=1e-6)
    np.testing.assert_allclose(np.sum(reverse * direction), central, rtol=1e-6)


@pytest.fixture(scope="module")
def pair():
    return icp.synthetic_pair(1500, rotation_deg=6.0, translation=0.08, noise=0.002,
                              same_samples=False, seed=4)  # fmt: skip


def _register(source, target, normals, search, **kw):
    return icp.point_to_plane(
        source, target, target_normals=normals, max_correspondence_distance=0.15,
        relative_fitness=1e-12, relative_rmse=1e-12, max_iterations=60, search=search, **kw,
    )  # fmt: skip


@pytest.fixture(scope="module")
def brute_result(pair):
    source, target, normals, _ = pair
    return _register(source, target, normals, "brute")


@pytest.mark.parametrize("search", ("grid", "kdtree", "auto"))
def test_point_to_plane_agrees_with_brute_force(pair, brute_result, search):
    source, target, normals, truth = pair
    result = _register(source, target, normals, search)
    assert result.status_name == "CONVERGED"
    np.testing.assert_allclose(
        result.transform.as_matrix(), brute_result.transform.as_matrix(), atol=1e-7
    )
    np.testing.assert_array_equal(result.correspondences, brute_result.correspondences)
    gap = np.asarray(result.transform.as_matrix()) - np.asarray(truth.as_matrix())
    assert np.abs(gap).max() < 1e-2


@pytest.mark.parametrize("search", BACKENDS)
def test_vmap_over_sources_sharing_a_target(pair, search):
    source, target, normals, _ = pair
    sources = jnp.stack([source, source + 0.003, source[::-1]])

    def one(s):
        return _register(s, target, normals, search, throw=False)

    batched = jax.vmap(one)(sources)
    for b in range(sources.shape[0]):
        single = one(sources[b])
        np.testing.assert_allclose(
            batched.transform.parameters()[b], single.transform.parameters(), atol=1e-10
        )
        np.testing.assert_array_equal(batched.correspondences[b], single.correspondences)


def test_vmap_over_targets_builds_one_host_tree_each(pair):
    source, target, _, _ = pair
    targets = jnp.stack([target, target + 0.01])
    host = _host_kdtree.host_library()
    index = jax.vmap(lambda t: _search.build_index(t, search="kdtree", library=host))(targets)
    assert index.tree.shape == (2,) and int(index.tree[0]) != int(index.tree[1])
    result = jax.vmap(lambda ix: _search.nearest(ix, source, radius=0.1))(index)
    for b in range(2):
        reference, _ = cKDTree(np.asarray(targets[b])).query(np.asarray(source), 1)
        within = reference <= 0.1
        np.testing.assert_allclose(result.distance[b][within], reference[within], atol=1e-12)


def test_vmap_groups_host_queries_by_tree_and_radius(pair):
    """Under `vmap` the host answers the whole batch in one call, one tree query per (tree,
    radius): elements that share a tree but not a radius, or a radius but not a tree, still get
    their own exact answers."""
    source, target, _, _ = pair
    targets = jnp.stack([target, target + 0.01, target])
    radii = jnp.asarray([0.1, 0.1, 0.03])
    host = _host_kdtree.host_library()
    index = jax.vmap(lambda t: _search.build_index(t, search="kdtree", library=host))(targets)
    assert int(index.tree[0]) == int(index.tree[2]) != int(index.tree[1])
    result = jax.jit(jax.vmap(lambda ix, r: _search.nearest(ix, source, radius=r)))(index, radii)
    for b in range(3):
        reference, _ = cKDTree(np.asarray(targets[b])).query(np.asarray(source), 1)
        within = reference <= float(radii[b])
        assert np.array_equal(np.isfinite(result.distance[b]), within)
        np.testing.assert_allclose(result.distance[b][within], reference[within], atol=1e-12)


def test_prebuilt_index_is_reused(pair):
    source, target, normals, _ = pair
    host = _host_kdtree.host_library()
    first = _search.build_index(target, search="kdtree", library=host)
    again = _search.build_index(target, search="kdtree", library=host)
    assert int(first.tree) == int(again.tree)  # the host registry found the same target
    reference = _register(source, target, normals, "kdtree")
    for index in (first, _search.build_index(target, search="grid", max_distance=0.15)):
        result = _register(source, target, normals, index)
        np.testing.assert_allclose(
            result.transform.parameters(), reference.transform.parameters(), atol=1e-12
        )
    small_grid = _search.build_index(target, search="grid", max_distance=0.05)
    with pytest.raises(ValueError, match="cell size"):
        _register(source, target, normals, small_grid)
    with pytest.raises(ValueError, match="points"):
        _register(source, target[:-1], normals[:-1], first)


def test_auto_rule():
    assert _search.resolve("auto", 10**6, platform="cpu") == "kdtree"
    assert _search.resolve("auto", 1000, platform="gpu") == "brute"
    assert _search.resolve("auto", 10**6, platform="gpu") == "grid"
    assert _search.resolve("auto", 10**6, has_radius=False, platform="gpu") == "brute"
    assert _search.resolve("grid", 10, platform="cpu") == "grid"


def test_bad_search_arguments(pair, monkeypatch):
    source, target, normals, _ = pair
    for name in ("octree", "graph"):  # (the graph's descent was removed: slower everywhere)
        with pytest.raises(ValueError, match=r"search must be one of \('auto', 'grid', 'kdtree'"):
            _register(source, target, normals, name)
    with pytest.raises(ValueError, match="max_distance"):
        _search.build_index(target, search="grid")
    with pytest.raises(ValueError, match="shape"):
        _search.build_index(target[:, :2], search="brute")
    with pytest.raises(TypeError, match="not a neighbour index"):
        _search.nearest((target,), source)
    with pytest.raises(ValueError, match="library"):
        _search.build_index(target, search="kdtree", library="flann")
    # The host tree refuses to run for another backend (checked while tracing).
    monkeypatch.setattr(_host_kdtree.jax, "default_backend", lambda: "gpu")
    with pytest.raises(ValueError, match="search='kdtree' runs on the host CPU"):
        jax.jit(lambda t: _search.build_index(t, search="kdtree"))(target)
