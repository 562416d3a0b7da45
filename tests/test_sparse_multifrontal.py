"""The host multifrontal block Cholesky of `lieax.factorgraph._multifrontal`: the update products
subtracted where their columns become pivots, the identity on padded pivots from the assembly,
the substitution's two ways of subtracting updates, and the pivot blocks' inverse factors."""

import jax.numpy as jnp
import numpy as np
import pytest

from lieax.factorgraph import _block_pattern, _host_triangular, _multifrontal


def random_system(n, extra, d, seed):
    """A connected random block pattern (a chain and `extra` random pairs), a diagonally dominant
    system on it, and its dense matrix."""
    rng = np.random.default_rng(seed)
    i = np.concatenate([np.arange(n - 1), rng.integers(0, n, extra)])
    j = np.concatenate([np.arange(1, n), rng.integers(0, n, extra)])
    keep = i != j
    return system_on_edges(n, d, i[keep], j[keep], rng)


def system_on_edges(n, d, i, j, rng):
    """The pattern of the block pairs `(i, j)`, a diagonally dominant (positive definite) system
    on it, its dense matrix and a right-hand side: `(pattern, diag, off, dense, rhs)`."""
    pattern, _, _ = _block_pattern.BlockPattern.from_edges(n, d, i, j)
    off = 0.3 * rng.normal(size=(pattern.num_pairs, d, d))
    a = rng.normal(size=(n, d, d))
    degree = np.bincount(np.concatenate([pattern.rows, pattern.cols]), minlength=n)
    diag = a @ np.swapaxes(a, 1, 2) + (2.0 * d * (degree + 1))[:, None, None] * np.eye(d)
    dense = np.asarray(_block_pattern.dense_matrix(pattern, jnp.asarray(diag), jnp.asarray(off)))
    return pattern, diag, off, dense, rng.normal(size=(n, d))


@pytest.mark.parametrize(("n", "extra", "d", "seed"), [(60, 90, 3, 0), (120, 200, 6, 1)])
def test_solve_matches_dense_with_shared_updates_and_padding(n, extra, d, seed):
    """Plans whose batches include padded fronts and fronts that share update blocks (the
    substitution's summed scatter) solve as the dense matrix does, and repeated solves reuse the
    work array without carrying anything over."""
    pattern, diag, off, dense, rhs = random_system(n, extra, d, seed)
    plan = _multifrontal.CholeskyPlan.analyze(pattern)
    assert any(batch.scatter is not None for batch in plan.batches)
    assert any(batch.scatter is None and batch.shape[2] for batch in plan.batches)
    padded = [(batch.pivot_index == n).any() for batch in plan.batches]
    assert any(padded)
    expected = np.linalg.solve(dense, rhs.ravel()).reshape(n, d)
    for _ in range(2):
        np.testing.assert_allclose(plan.solve(diag, off, rhs), expected, rtol=1e-9, atol=1e-12)


def test_not_positive_definite_is_nan():
    pattern, diag, off, _, rhs = random_system(40, 60, 3, 2)
    plan = _multifrontal.CholeskyPlan.analyze(pattern)
    diag = diag.copy()
    diag[plan.order[0]] *= -1.0  # the first eliminated block: a pivot of a leaf front
    assert np.all(np.isnan(plan.solve(diag, off, rhs)))
    diag[plan.order[0]] *= -1.0
    diag[plan.order[-1]] = -diag[plan.order[-1]]  # a pivot of the root
    assert np.all(np.isnan(plan.solve(diag, off, rhs)))


@pytest.mark.parametrize("order", [5, 9, 30, 36, 63, 64, 90])
def test_cholesky_inverse(order):
    """`_cholesky_inverse` reads only the lower triangle and returns the inverse factor, by
    LAPACK's `potrf` and `trtri` (orders 9 to 63) or NumPy; a matrix that is not positive
    definite raises `LinAlgError`."""
    rng = np.random.default_rng(order)
    a = rng.normal(size=(3, order, order))
    matrix = a @ np.swapaxes(a, 1, 2) + order * np.eye(order)
    garbled = np.tril(matrix) + np.triu(rng.normal(size=matrix.shape), 1)
    inverse = _host_triangular._cholesky_inverse(garbled)
    np.testing.assert_allclose(
        inverse, np.linalg.inv(np.linalg.cholesky(matrix)), rtol=1e-10, atol=1e-12
    )
    assert np.all(np.triu(inverse, 1) == 0.0)
    matrix[1] = -matrix[1]
    with pytest.raises(np.linalg.LinAlgError):
        _host_triangular._cholesky_inverse(matrix)


@pytest.mark.parametrize("order", [6, 63, 64, 180])
def test_cholesky_solve(order):
    """`_cholesky_solve` (LAPACK's `potrs`, the roots' two substitutions in one call)."""
    rng = np.random.default_rng(order)
    a = rng.normal(size=(2, order, order))
    matrix = a @ np.swapaxes(a, 1, 2) + order * np.eye(order)
    rhs = rng.normal(size=(2, order, 1))
    x = _host_triangular._cholesky_solve(np.linalg.cholesky(matrix), rhs)
    np.testing.assert_allclose(matrix @ x, rhs, atol=1e-10)
