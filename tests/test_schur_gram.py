r"""Tests of the Schur complement's closed forms in lieax.factorgraph: the batched 3×3 inverse
(`_linear.spd_inverse`) against `jnp.linalg.inv`, the chunked Gram sums (`_gram`) against one
product per term and a segment sum, and `schur_solve` on a bundle adjustment against dense
elimination of the whole system; the camera blocks of the normal equations (summed by chunks)
against the dense $J^\top J$.
"""

import jax
import jax.numpy as jnp
import numpy as np
import pytest

from lieax import ba
from lieax.factorgraph import Factor, FactorGraph, Var, _gram
from lieax.factorgraph._assembly import evaluate, linearize
from lieax.factorgraph._linear import schur_solve, solve_system, spd_inverse
from lieax.factorgraph._structure import schur_layout

jax.config.update("jax_enable_x64", True)


def test_spd_inverse_matches_linalg_inv():
    rng = np.random.default_rng(0)
    for d in (2, 3, 4):
        m = rng.normal(size=(50, d, d))
        # condition numbers up to ~1e6
        a = m @ np.swapaxes(m, 1, 2) + np.logspace(-6, 0, 50)[:, None, None] * np.eye(d)
        inverse = np.asarray(spd_inverse(jnp.asarray(a)))
        expected = np.linalg.inv(a)
        scale = np.abs(expected).max(axis=(1, 2), keepdims=True)
        np.testing.assert_array_less(np.abs(inverse - expected) / scale, 1e-8)


def test_spd_inverse_is_nan_where_not_positive_definite():
    a = np.stack(
        [
            np.eye(3),
            np.diag([1.0, -1.0, 1.0]),  # indefinite (second leading minor negative)
            np.diag([-1.0, -1.0, 1.0]),  # det > 0 but not positive definite
            np.zeros((3, 3)),
            np.array([[1.0, 2.0, 0.0], [2.0, 1.0, 0.0], [0.0, 0.0, -1.0]]),  # det > 0
        ]
    )
    inverse = np.asarray(spd_inverse(jnp.asarray(a)))
    assert np.allclose(inverse[0], np.eye(3))
    assert np.all(np.isnan(inverse[1:]))


def _direct(u, v, segment, count, x, y):
    terms = np.einsum("mka,mkb->mab", x[u], y[v])
    out = np.zeros((count, x.shape[2], y.shape[2]))
    np.add.at(out, segment, terms)
    return out


@pytest.mark.parametrize("chunk", [None, 1, 3, 8])
def test_gram_sum_matches_products_and_segment_sum(chunk, monkeypatch):
    rng = np.random.default_rng(1)
    m, count = 200, 7
    x, y = rng.normal(size=(m, 3, 9)), rng.normal(size=(m + 5, 3, 4))
    u, v = rng.integers(0, m, 300), rng.integers(0, m + 5, 300)
    # skewed runs, slot 5 empty
    segment = rng.choice([0, 1, 2, 3, 4, 6], size=300, p=[0.5, 0.2, 0.1, 0.1, 0.05, 0.05])
    plan = _gram.gram_plan(u, v, segment, count, m, m + 5, chunk=chunk)
    expected = _direct(u, v, segment, count, x, y)
    np.testing.assert_allclose(
        _gram.gram_sum(plan, jnp.asarray(x), jnp.asarray(y)), expected, rtol=1e-12, atol=1e-12
    )
    # several blocks of chunks through the scan (the last one padded)
    monkeypatch.setattr(_gram, "_BLOCK_ENTRIES", 500)
    np.testing.assert_allclose(
        _gram.gram_sum(plan, jnp.asarray(x), jnp.asarray(y)), expected, rtol=1e-12, atol=1e-12
    )


@pytest.mark.parametrize("k", [1, 2, 3, 9])
def test_small_products_match_matmul(k):
    # elementwise sums up to `_UNROLLED` terms, products beyond (k = 9)
    rng = np.random.default_rng(k)
    a, b = jnp.asarray(rng.normal(size=(7, 4, k))), jnp.asarray(rng.normal(size=(7, k, 5)))
    at, x = jnp.swapaxes(a, 1, 2), jnp.asarray(rng.normal(size=(7, k)))
    np.testing.assert_allclose(_gram.small_matmul(a, b), a @ b, rtol=1e-13, atol=1e-13)
    np.testing.assert_allclose(_gram.small_tmatmul(at, b), a @ b, rtol=1e-13, atol=1e-13)
    np.testing.assert_allclose(
        _gram.small_matvec(a, x), (a @ x[..., None])[..., 0], rtol=1e-13, atol=1e-13
    )


def test_gram_plan_without_terms():
    plan = _gram.gram_plan([], [], [], 3, 0, 0)
    out = _gram.gram_sum(plan, jnp.zeros((0, 2, 3)), jnp.zeros((0, 2, 2)))
    assert out.shape == (3, 3, 2) and not np.any(out)


@pytest.fixture(scope="module")
def bundle():
    """A small bundle adjustment whose cameras collect more than 16 observations each (their
    diagonal blocks are summed by chunks), linearized at a perturbed start."""
    problem = ba.synthetic_bal(4, 60, 200, seed=3).problem
    pose, intrinsics = problem.camera_variables(jnp.float64)
    cameras = Var((pose, intrinsics), name="cameras")
    points = Var(jnp.asarray(problem.points), name="points")
    factor = Factor(
        ba.camera_residual,
        (cameras[problem.camera_indices], points[problem.point_indices]),
        jnp.asarray(problem.observations),
        jacobian_fn=ba.camera_jacobians,
        name="reprojection",
    )
    graph = FactorGraph([factor], check_gauge=False)
    _, diag, off, grad = linearize(
        graph.layout, graph.factors, graph.plans, graph.initial_values, graph.data
    )
    return graph, diag, off, grad


def test_camera_blocks_match_dense_normal_equations(bundle):
    graph, diag, off, grad = bundle
    assert graph.plans[0].grams[0] is not None  # the chunked path is the one tested
    _, parts = evaluate(graph.factors, graph.plans, graph.initial_values, graph.data)
    r, (a_cam, _), _ = parts[0]
    r, a_cam = np.asarray(r), np.asarray(a_cam)
    cams = np.asarray(graph.plans[0].indices[0])
    expected = np.zeros((graph.layout.counts[0], 9, 9))
    np.add.at(expected, cams, np.einsum("mka,mkb->mab", a_cam, a_cam))
    expected_grad = np.zeros((graph.layout.counts[0], 9))
    np.add.at(expected_grad, cams, np.einsum("mka,mk->ma", a_cam, r))
    np.testing.assert_allclose(diag[0], expected, rtol=1e-10, atol=1e-8 * np.abs(expected).max())
    np.testing.assert_allclose(grad[0], expected_grad, rtol=1e-10, atol=1e-8)


def test_schur_solve_matches_dense_elimination(bundle):
    graph, diag, off, grad = bundle
    layout = graph.layout
    damped = tuple(d + 1e-3 * np.eye(d.shape[-1]) * np.abs(d).max() for d in diag)
    rhs = tuple(-g for g in grad)
    plan = schur_layout(layout, 1, ["cameras", "points"])
    expected = solve_system(layout, "dense", damped, off, rhs)
    for method in ("dense", "cholesky"):
        x = schur_solve(layout, plan, method, damped, off, rhs)
        for xk, ek in zip(x, expected):
            np.testing.assert_allclose(xk, ek, rtol=1e-7, atol=1e-9 * np.abs(ek).max())
