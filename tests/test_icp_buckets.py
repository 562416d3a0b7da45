"""Capacity buckets (`lieax.icp._batch.bucket_size`): ICP pads clouds of new sizes to a few
shapes, so that a stream of clouds of varying sizes compiles a few loops, not one per size, and
the padded call gives the unpadded call's results."""

import numpy as np
import pytest

from lieax import icp
from lieax.icp import _loop, _normals
from lieax.icp._batch import CHUNK_POINTS, bucket_size, chunk_size, pad_to_bucket


def test_bucket_sizes():
    # 2^(b-1) < n <= 2^b is padded to a multiple of 2^(b-3): 5, 6, 7 or 8 times it.
    expected = {1: 1, 8: 8, 9: 10, 300: 320, 3000: 3072, 3100: 3584, 4097: 5120, 25_000: 28_672}
    assert {n: bucket_size(n) for n in expected} == expected
    sizes = np.arange(9, 1 << 16)
    buckets = np.array([bucket_size(int(n)) for n in sizes])
    assert np.all(buckets >= sizes) and np.all(buckets <= 1.25 * sizes)
    assert np.all(np.diff(buckets) >= 0)
    for b in range(4, 16):  # four shapes per doubling
        assert len(set(buckets[(sizes > 1 << (b - 1)) & (sizes <= 1 << b)])) == 4


def test_pad_to_bucket_masks_the_new_rows():
    points = np.ones((9, 3))
    padded, mask, normals, missing = pad_to_bucket(points, np.ones(9, bool), points, None)
    assert padded.shape == normals.shape == (10, 3) and missing is None
    np.testing.assert_array_equal(np.asarray(mask), [True] * 9 + [False])
    np.testing.assert_array_equal(np.asarray(padded)[9], 0.0)


@pytest.fixture(scope="module")
def pair():
    return icp.synthetic_pair(300, rotation_deg=8.0, translation=0.08, noise=0.002, seed=3)


@pytest.mark.parametrize("kind", ["point_to_plane", "point_to_point", "gicp"])
def test_padding_does_not_change_results(pair, kind):
    """300 points padded to 320 (and the target normals or the covariances estimated on the padded
    clouds) give the unpadded results: the pose to 1e-12, the same matches, statistics and
    iterations."""
    source, target, _, _ = pair
    register = getattr(icp, kind)
    padded = register(source, target, max_correspondence_distance=0.4)
    exact = register(source, target, max_correspondence_distance=0.4, buckets=False)
    assert padded.status_name == exact.status_name == "CONVERGED"
    difference = padded.transform.rminus(exact.transform)
    assert float(np.max(np.abs(np.asarray(difference)))) < 1e-12
    assert padded.correspondences.shape == (300,)
    np.testing.assert_array_equal(
        np.asarray(padded.correspondences), np.asarray(exact.correspondences)
    )
    assert int(padded.iterations) == int(exact.iterations)
    assert float(padded.fitness) == float(exact.fitness)
    assert float(padded.inlier_rmse) == pytest.approx(float(exact.inlier_rmse), rel=1e-12)


def test_a_stream_of_sizes_compiles_one_loop():
    """20 clouds of 321 to 384 points (one bucket), target normals estimated: at most one new
    compilation of the loop and of the normals (their neighbourhoods and their eigenvectors), where exact shapes would need up to twenty of
    each. (A stream of 3000 to 4500 points spans four buckets: `benchmarks/icp_buckets.py`.)"""
    rng = np.random.default_rng(0)
    sizes = rng.integers(321, 385, size=20)
    assert len(set(sizes)) > 10 and {bucket_size(int(n)) for n in sizes} == {384}
    compiled = (_loop.solve, _normals._normals, _normals._kdtree_neighbourhoods_call)
    before = [f._cache_size() for f in compiled]
    for k, n in enumerate(sizes):
        source, target, _, _ = icp.synthetic_pair(
            int(n), rotation_deg=5.0, translation=0.05, seed=int(k)
        )
        result = icp.point_to_plane(source, target, max_correspondence_distance=0.4)
        assert result.status_name == "CONVERGED" and result.correspondences.shape == (n,)
    assert all(f._cache_size() - n <= 1 for f, n in zip(compiled, before))


def test_chunk_sizes():
    # (about CHUNK_POINTS source points per chunk, at least one element, at most the batch)
    assert chunk_size(500, 64) == CHUNK_POINTS // 500
    assert chunk_size(10 * CHUNK_POINTS, 64) == 1
    assert chunk_size(10, 3) == 3


SHIFTS = np.linspace(-0.01, 0.01, 5)


def shifted_registration(pair):
    """`(register, pose_sum)`: point-to-plane ICP of the pair's source moved by a shift, and a
    weighted sum of its pose's parameters (a shift moves the translation; 1e-3 of it reaches the
    rotation)."""
    import jax.numpy as jnp

    source, target, normals, _ = pair

    def register(shift):
        return icp.point_to_plane(
            source + shift, target, target_normals=normals, max_correspondence_distance=0.2,
            throw=False,
        )  # fmt: skip

    def pose_sum(shift):
        return jnp.sum(register(shift).transform.parameters()[1:] * jnp.arange(1.0, 7.0))

    return register, pose_sum


@pytest.fixture(scope="module")
def each_elements_result(pair):
    """Each shift's own (unbatched, so unchunked) call: the pose, the iterations and the
    derivative (`jax.grad`, op by op) of `pose_sum`; once for the three chunk sizes."""
    import jax

    register, pose_sum = shifted_registration(pair)
    results = [register(shift) for shift in SHIFTS]
    return (
        [np.asarray(result.transform.parameters()) for result in results],
        [int(result.iterations) for result in results],
        [np.asarray(jax.grad(pose_sum)(shift)) for shift in SHIFTS],
    )


@pytest.mark.parametrize("chunk", [1, 2, 5])
def test_a_vmapped_batch_in_chunks_gives_each_elements_result(
    pair, each_elements_result, monkeypatch, chunk
):
    """A batch of 5 in chunks of 1 (one at a time), 2 (two chunks and a remainder) and 5 (all in
    lockstep): every element's result is that of its own call, the derivative with respect to the
    source too (the chunking applies to the loop only; the implicit derivative is vmapped). The
    batch and its derivatives are one program per chunk size."""
    import jax

    from lieax.icp import _batch

    register, pose_sum = shifted_registration(pair)
    monkeypatch.setattr(_batch, "CHUNK_POINTS", chunk * bucket_size(pair[0].shape[0]))

    @jax.jit
    def batched_and_derivatives(shifts):
        return jax.vmap(register)(shifts), jax.vmap(jax.grad(pose_sum))(shifts)

    batched, derivatives = batched_and_derivatives(SHIFTS)
    poses, iterations, gradients = each_elements_result
    for b in range(5):
        np.testing.assert_allclose(batched.transform.parameters()[b], poses[b], atol=1e-10)
        assert int(batched.iterations[b]) == iterations[b]
        np.testing.assert_allclose(derivatives[b], gradients[b], rtol=1e-8)
