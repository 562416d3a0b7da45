"""The native k-d tree (`lieax.icp._native_kdtree`, `csrc/kdtree.cc`): its answers against brute
force and against the host tree (pykdtree's or SciPy's) for radius searches with masks, ICP's
warm-started tracking, the spacing, k-nearest neighbourhoods and GICP's covariance sums, in
float32 and float64, batched under `vmap` (one custom call), on empty, fully masked and repeated
targets; ICP with either tree; and the ICP demo's registration and a GICP served from JAX's
persistent compilation cache in a second process."""

import os
import textwrap
import time

import jax
import jax.numpy as jnp
import numpy as np
import pytest
from _child import child_output

from lieax import _native, icp
from lieax.icp import _covariances, _host_kdtree, _native_kdtree, _search

pytestmark = pytest.mark.skipif(
    not _native.available(), reason="the native library is not built (see setup.py)"
)
HOST = _host_kdtree.host_library()


def _brute(target, valid, queries):
    """`(n_queries, n_target)` squared distances in float64, `inf` to invalid target rows."""
    gaps = queries[:, None, :].astype(np.float64) - target[None, :, :].astype(np.float64)
    d2 = np.sum(gaps * gaps, axis=-1)
    return np.where(valid[None, :], d2, np.inf)


def _cloud(rng, n, dtype, repeats=0):
    """`n` points on a few clusters, the first `repeats` of them one repeated point."""
    centres = rng.uniform(-1, 1, (5, 3))
    points = centres[rng.integers(0, 5, n)] + 0.2 * rng.normal(size=(n, 3))
    points[:repeats] = points[0]
    return points.astype(dtype)


@jax.jit
def _match(index, queries, radius, mask):
    return _host_kdtree.nearest_in_kdtree(index, queries, radius, mask=mask)


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
@pytest.mark.parametrize("repeats", [0, 40])
def test_nearest_within_radius_equals_brute_force_and_the_host_tree(dtype, repeats):
    """Every query gets the nearest valid target point within the radius (brute force's
    distance; the host tree's slot unless another point lies as near), none beyond it or when
    masked; invalid target rows (masked, not finite) are never matched."""
    rng = np.random.default_rng(1)
    target = _cloud(rng, 700, dtype, repeats)
    target[5] = np.nan
    valid = (rng.uniform(size=700) > 0.2) & np.all(np.isfinite(target), axis=1)
    queries = _cloud(rng, 300, dtype)
    queries[:20] = target[rng.integers(0, 700, 20)]  # (distance 0 to some of them)
    mask = rng.uniform(size=300) > 0.1
    radius = 0.15
    ours, host = (
        _search.build_index(jnp.asarray(target), jnp.asarray(valid), search="kdtree", library=lib)
        for lib in ("native", HOST)
    )
    assert _host_kdtree.is_native(ours) and not _host_kdtree.is_native(host)
    slot, d2 = (np.asarray(x) for x in _match(ours, queries, radius, mask))
    host_slot, _ = (np.asarray(x) for x in _match(host, queries, radius, mask))
    brute = _brute(target, valid, queries)
    best = np.min(brute, axis=1)
    within = mask & (best <= radius**2)
    assert np.array_equal(np.isfinite(d2), within)
    tolerance = 1e-12 if dtype == np.float64 else 1e-6
    np.testing.assert_allclose(brute[within, slot[within]], best[within], rtol=0, atol=tolerance)
    assert np.all(valid[slot[within]])
    unique = np.sum(brute <= best[:, None] + tolerance, axis=1) == 1
    assert np.array_equal(slot[within & unique], host_slot[within & unique])


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_empty_and_fully_masked_targets_match_nothing(dtype):
    rng = np.random.default_rng(2)
    target, queries = _cloud(rng, 50, dtype), _cloud(rng, 20, dtype)
    for valid in (np.zeros(50, bool), np.full(50, True)):
        if valid.all():
            target = np.full_like(target, np.inf)  # (not finite: invalid as well)
        index = _search.build_index(jnp.asarray(target), jnp.asarray(valid), search="kdtree")
        slot, d2 = _match(index, queries, jnp.inf, np.ones(20, bool))
        assert np.all(np.isinf(d2)) and np.all(np.asarray(slot) == 0)
        np.testing.assert_array_equal(_host_kdtree.kdtree_spacing(index), np.zeros(50, dtype))
        warm = _host_kdtree.cold_start(20, dtype)
        slot, d2, warm = _host_kdtree.track_in_kdtree(index, queries, 0.5, warm)
        assert np.all(np.isinf(d2)) and np.all(np.asarray(warm.slot) == -1)
        np.testing.assert_array_equal(warm.allowance, np.full(20, 0.5, dtype))
        found = _native_kdtree.neighbours(jnp.asarray(target), jnp.asarray(valid & False), 4)
        assert np.all(np.asarray(found) == -1)


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_tracking_equals_the_host_trees(dtype):
    """`track_in_kdtree` over large, then shrinking moves: the native tree's slots, allowances and
    gaps are the host tree's (pykdtree's or SciPy's), the second-nearest distance included;
    a single valid target point gets the allowance (2r - d) / 2."""
    rng = np.random.default_rng(3)
    target = _cloud(rng, 1200, dtype, repeats=12)
    queries = _cloud(rng, 400, dtype)
    mask = rng.uniform(size=400) > 0.1
    radius = 0.1
    indices = [
        _search.build_index(jnp.asarray(target), search="kdtree", library=lib)
        for lib in ("native", HOST)
    ]
    track = jax.jit(
        lambda ix, q, w: _host_kdtree.track_in_kdtree(ix, q, radius, w, mask=jnp.asarray(mask))
    )
    warms = [_host_kdtree.cold_start(400, dtype)] * 2
    tolerance = 1e-12 if dtype == np.float64 else 1e-5
    for step in range(6):
        (slot, d2, warm), (host_slot, host_d2, host_warm) = (
            track(ix, jnp.asarray(queries), w) for ix, w in zip(indices, warms)
        )
        unique = np.isclose(np.asarray(warm.allowance), np.asarray(host_warm.allowance))
        assert np.mean(unique) > 0.97  # (a tie in the nearest or second-nearest changes little)
        np.testing.assert_array_equal(np.asarray(slot)[unique], np.asarray(host_slot)[unique])
        np.testing.assert_allclose(d2, host_d2, rtol=0, atol=tolerance)
        np.testing.assert_allclose(warm.gap, host_warm.gap, rtol=1e-4)
        warms = [warm, host_warm]
        scale = 0.1 if step < 2 else 0.01 / step**2
        queries = queries + rng.normal(scale=scale, size=queries.shape).astype(dtype)
    single = _search.build_index(jnp.asarray(target[:1]), search="kdtree")
    _, d2, warm = _host_kdtree.track_in_kdtree(
        single, queries, radius, _host_kdtree.cold_start(400, dtype)
    )
    d = np.linalg.norm(queries.astype(np.float64) - target[0], axis=1)
    near = d < 2 * radius * (1 - 1e-5)
    np.testing.assert_allclose(np.asarray(warm.allowance)[near], (2 * radius - d[near]) / 2,
                               rtol=0, atol=tolerance)  # fmt: skip


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_neighbourhoods_spacing_and_covariances_equal_brute_force(dtype):
    """k nearest valid rows (itself among them) and the spacing against brute force, on a cloud
    with more repeats of one point than a leaf holds; the covariance sums against the host's."""
    rng = np.random.default_rng(4)
    points = _cloud(rng, 500, dtype, repeats=30)
    valid = np.arange(500) % 7 != 3
    k = 12
    found = np.asarray(_native_kdtree.neighbours(jnp.asarray(points), jnp.asarray(valid), k))
    brute = _brute(points, valid, points)
    expected = np.sort(brute[valid], axis=1)[:, :k]
    got = np.take_along_axis(brute[valid], found[valid], axis=1)
    tolerance = 1e-12 if dtype == np.float64 else 1e-6
    np.testing.assert_allclose(got, expected, rtol=0, atol=tolerance)
    assert np.all(np.diff(got, axis=1) >= -tolerance) and np.all(valid[found[valid]])
    assert np.all(found[~valid] == -1)
    index = _search.build_index(jnp.asarray(points), jnp.asarray(valid), search="kdtree")
    spacing = np.asarray(_host_kdtree.kdtree_spacing(index))
    np.testing.assert_allclose(spacing[valid], np.sqrt(expected[:, 1]), rtol=0, atol=1e-6)
    assert np.all(spacing[~valid] == 0)
    entries = np.asarray(_native_kdtree.covariance_entries(jnp.asarray(points), valid, 20))
    host = _covariances._host_covariance_entries(points, valid, 20, HOST)
    np.testing.assert_allclose(entries, host, rtol=0, atol=1e-12 if dtype == np.float64 else 1e-7)


def test_vmap_is_one_call_per_batch_with_shared_or_own_trees():
    """Under `vmap` the build and the queries are one custom call each, batched targets or a
    shared one alike, and every element gets its own exact answers."""
    rng = np.random.default_rng(5)
    targets = np.stack([_cloud(rng, 400, np.float64) for _ in range(3)])
    queries = np.stack([_cloud(rng, 150, np.float64) for _ in range(3)])
    radii = np.array([0.1, 0.2, 0.05])

    def one(target, q, r):
        index = _search.build_index(target, search="kdtree")
        return _host_kdtree.nearest_in_kdtree(index, q, r)

    batched = jax.jit(jax.vmap(one))
    text = batched.lower(targets, queries, radii).as_text()
    assert text.count("lieax_kdtree_build") == 1 and text.count("lieax_kdtree_nearest") == 1
    slot, d2 = batched(targets, queries, radii)
    shared_index = _search.build_index(jnp.asarray(targets[0]), search="kdtree")
    shared = jax.jit(jax.vmap(lambda q: _host_kdtree.nearest_in_kdtree(shared_index, q, 0.1)))
    shared_slot, _ = shared(queries)
    for b in range(3):
        brute = _brute(targets[b], np.ones(400, bool), queries[b])
        best = np.min(brute, axis=1)
        within = best <= radii[b] ** 2
        np.testing.assert_array_equal(np.asarray(slot[b])[within], np.argmin(brute, 1)[within])
        np.testing.assert_allclose(np.asarray(d2[b])[within], best[within], rtol=1e-12)
        brute = _brute(targets[0], np.ones(400, bool), queries[b])
        within = np.min(brute, axis=1) <= 0.01
        np.testing.assert_array_equal(np.asarray(shared_slot[b])[within],
                                      np.argmin(brute, 1)[within])  # fmt: skip


@pytest.fixture(scope="module")
def pair():
    return icp.synthetic_pair(1500, rotation_deg=6.0, translation=0.08, noise=0.002,
                              same_samples=False, seed=4)  # fmt: skip


def test_icp_with_the_native_or_the_host_tree_agrees(pair):
    """Point-to-plane and GICP with an index prebuilt on the native tree or the host tree: the
    same matches and poses (the tolerances of the search tests)."""
    source, target, normals, _ = pair
    results = {}
    for library in ("native", HOST):
        index = _search.build_index(target, search="kdtree", library=library)
        plane = icp.point_to_plane(source, target, target_normals=normals,
                                   max_correspondence_distance=0.15, search=index)  # fmt: skip
        general = icp.gicp(source, target, max_correspondence_distance=0.15, search=index)
        results[library] = (plane, general)
    for ours, host in zip(results["native"], results[HOST]):
        assert ours.status_name == host.status_name == "CONVERGED"
        np.testing.assert_allclose(ours.transform.parameters(), host.transform.parameters(),
                                   atol=1e-12)  # fmt: skip
        np.testing.assert_array_equal(ours.correspondences, host.correspondences)


def test_bad_dtypes_and_a_missing_library_are_named(monkeypatch):
    with pytest.raises(ValueError, match="takes float32 or float64 points, got float16"):
        _search.build_index(jnp.zeros((4, 3), jnp.float16), search="kdtree", library="native")
    assert _host_kdtree.default_library(jnp.float16) == HOST
    monkeypatch.setattr(_native, "available", lambda: False)
    assert _host_kdtree.default_library(jnp.float64) == HOST
    with pytest.raises(ValueError, match="needs the native library"):
        _search.build_index(jnp.zeros((4, 3)), search="kdtree", library="native")


def test_the_thread_setting_reaches_the_library():
    """`lieax.threads` / `lieax.set_threads` hand their cap to the native tree (0: one thread
    per core), restored after the block."""
    import lieax

    library = _native.library()
    before = library.LieaxThreads()
    with lieax.threads(1):
        assert library.LieaxThreads() == 1
        with lieax.threads(None):
            assert library.LieaxThreads() == 0
        assert library.LieaxThreads() == 1
    assert library.LieaxThreads() == before == (lieax.get_threads() or 0)


@pytest.mark.parametrize("dtype", [np.float32, np.float64])
def test_a_tree_built_on_several_threads_is_the_tree_built_on_one(dtype):
    """A large tree builds its subtrees on several threads (nodes of 65,536 points or more) into
    exactly the arrays one thread builds (the same preorder numbering), its repeated points
    and masked rows included; so do the neighbourhoods (k-NN) that build their own trees."""
    import lieax

    rng = np.random.default_rng(7)
    points = _cloud(rng, 150_000, dtype, repeats=3000)
    valid = rng.random(len(points)) > 0.05
    build = jax.jit(_native_kdtree.build)
    neighbours = jax.jit(_native_kdtree.neighbours, static_argnums=2)
    with lieax.threads(1):
        one = build(points, valid)
        one_knn = neighbours(points, valid, 8)
    with lieax.threads(4):  # more threads than cores: the split does not depend on them
        several = build(points, valid)
        several_knn = neighbours(points, valid, 8)
    for a, b in zip(jax.tree.leaves(one), jax.tree.leaves(several)):
        np.testing.assert_array_equal(np.asarray(a), np.asarray(b))
    np.testing.assert_array_equal(np.asarray(one_knn), np.asarray(several_knn))


def test_calls_from_several_threads_share_the_helpers_and_agree_with_one_thread():
    """Parallel loops started at once (Python threads here; XLA's own threads in a program) take
    helper threads from one pool (`csrc/parallel.h`): each call's answers are those of a call on
    one thread, for queries (40,000 of them, past `PARALLEL_NEIGHBOURS`) and for a batch of two
    builds of 40,000 points (spread over the trees). Afterwards no thread spins."""
    import threading

    import lieax

    rng = np.random.default_rng(11)
    points = _cloud(rng, 40_000, np.float64, repeats=0)
    clouds = np.stack([points, _cloud(rng, 40_000, np.float64, repeats=0)])
    queries = points + rng.normal(0.0, 0.01, points.shape)
    active = np.ones(len(queries), bool)
    build = jax.jit(_native_kdtree.build)
    builds = jax.jit(jax.vmap(_native_kdtree.build))
    nearest = jax.jit(_native_kdtree.nearest)
    valid = np.ones(clouds.shape[:2], bool)
    with lieax.threads(1):
        tree = build(points, valid[0])

    def answer():
        found = (nearest(tree, queries, 0.05, active), builds(clouds, valid))
        return jax.tree.map(np.asarray, found)

    with lieax.threads(1):
        expected = answer()
    answers, errors = [], []

    def call():
        try:
            answers.append(answer())
        except Exception as error:  # (reported below: an assertion in a thread is lost)
            errors.append(error)

    with lieax.threads(4):
        callers = [threading.Thread(target=call) for _ in range(4)]
        for caller in callers:
            caller.start()
        for caller in callers:
            caller.join()
    assert not errors and len(answers) == len(callers)
    for got in answers:
        for a, b in zip(jax.tree.leaves(expected), jax.tree.leaves(got)):
            np.testing.assert_array_equal(a, b)
    if os.path.isdir("/proc/self/task"):  # (Linux: per-thread CPU times)
        _assert_no_thread_spins()


def _assert_no_thread_spins():
    """No thread of this process uses CPU time while nothing runs: the helpers sleep (Linux's
    per-thread CPU times, in clock ticks, over 0.3 s after a 0.1 s rest)."""

    def ticks():
        out = {}
        for tid in os.listdir("/proc/self/task"):
            try:
                with open(f"/proc/self/task/{tid}/stat") as stat:
                    fields = stat.read().rsplit(")", 1)[1].split()
            except FileNotFoundError:  # (a thread that ended meanwhile)
                continue
            out[tid] = int(fields[11]) + int(fields[12])  # utime + stime
        return out

    time.sleep(0.1)
    before = ticks()
    time.sleep(0.3)
    after = ticks()
    used = {tid: after[tid] - before.get(tid, 0) for tid in after}
    # 0.3 s is 30 ticks at the usual 100 per second: a spinning thread would show about that many.
    assert sum(used.values()) <= 3, used


CHILD = textwrap.dedent(
    """
    import sys, jax
    jax.config.update("jax_enable_x64", True)
    import jax.numpy as jnp, lieax
    from lieax import icp
    lieax.enable_compilation_cache(sys.argv[1])
    compiled, hit = [0], [False]

    def event(name, **kw):
        if name == "/jax/compilation_cache/cache_hits":
            hit[0] = True

    def duration(name, seconds, **kw):
        if name == "/jax/core/compile/backend_compile_duration":
            compiled[0] += not hit[0]
            hit[0] = False

    jax.monitoring.register_event_listener(event)
    jax.monitoring.register_event_duration_secs_listener(duration)
    source, target, normals, _ = icp.synthetic_pair(
        600, rotation_deg=10.0, translation=0.1, noise=0.002, same_samples=False, seed=0)
    source, target = jnp.asarray(source), jnp.asarray(target)
    compiled[0] = 0  # (the setup's programs aside)
    plane = icp.point_to_plane(source, target, target_normals=normals,
                               max_correspondence_distance=0.1, max_iterations=30)
    general = icp.gicp(source, target, max_correspondence_distance=0.1)
    assert plane.status_name == general.status_name == "CONVERGED"
    print(compiled[0])
    """
)


def test_icp_and_gicp_programs_are_served_from_the_persistent_cache(tmp_path):
    """The ICP demo's registration (point-to-plane, defaults: the k-d tree search) and a GICP
    (covariances and matches by the k-d tree) compile nothing in a second process: their
    programs hold custom calls, not Python callbacks, and lieax's store (the loops, the normals,
    the covariances: loaded with the k-d tree's targets registered first) and JAX's persistent
    cache (the rest) keep them."""
    run = lambda: child_output(CHILD, tmp_path).split()[-1]
    assert int(run()) > 0  # first process: compiled and written
    assert run() == "0"  # second process: every program read back
