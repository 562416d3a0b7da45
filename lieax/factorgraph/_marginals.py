r"""Marginal covariances: blocks of $H^{-1}$ at a solution (GTSAM's
`Marginals.marginalCovariance`, Ceres' `Covariance`).

$H = J^\top W J$ is the Gauss-Newton matrix of the whitened, reweighted residuals at the given
values, so the covariance of instance $a$ is the diagonal block $(H^{-1})_{aa}$ in its right-local
tangent coordinates (translation first for poses, as everywhere in lieax; GTSAM orders Pose3's
rotation first). Small graphs invert the dense $H$; larger ones factor it once with the
multifrontal `CholeskyPlan` and solve for the unit right-hand sides of the requested blocks.
"""

from collections.abc import Sequence

import numpy as np
from jax.typing import ArrayLike

from .._typing import PyTree
from ._dense_solve import gathered_matrix
from ._graph import FactorGraph
from ._variables import Var

_DENSE_LIMIT = 2000


def marginal_covariances(
    graph: FactorGraph,
    values: Sequence[PyTree],
    var: Var,
    indices: ArrayLike | Sequence[int] | None = None,
    *,
    data: Sequence[PyTree] | None = None,
    method: str = "auto",
) -> np.ndarray:
    """The marginal covariances of instances `indices` (default all) of `var` at `values`.

    **Arguments:**

    - `graph`: the `FactorGraph`.
    - `values`: the values (a `SolveResult.values` tuple), in the order of `graph.variables`.
    - `var`: the `Var` whose instances are wanted.
    - `indices`: instance indices (default all).
    - `data`: factor data as `FactorGraph.solve` takes it (default the factors').
    - `method`: `"dense"`, `"cholesky"` or `"auto"` (dense up to 2000 padded unknowns).

    **Returns:** a numpy array `(len(indices), d, d)`; zero for fixed instances.

    $H$ comes from the graph's compiled solve loop, stopped after it evaluated `values`
    (`FactorGraph._linearized_system`): after `solve`, this compiles nothing; the rest is NumPy.
    """
    layout = graph.layout
    k = graph.index(var)
    indices = np.arange(var.count) if indices is None else np.asarray(indices).reshape(-1)
    if np.any((indices < 0) | (indices >= var.count)):
        raise ValueError(f"indices out of range for {var.name!r} with {var.count} instances.")
    if method not in ("auto", "dense", "cholesky"):
        raise ValueError(f"method must be 'auto', 'dense' or 'cholesky', got {method!r}.")
    if method == "auto":
        method = "dense" if layout.padded_unknowns <= _DENSE_LIMIT else "cholesky"
    graph._check_x64()
    diag, off, _ = graph._linearized_system(tuple(values), graph._data(data))
    diag, off = padded_blocks(layout, diag, off)
    D, d = layout.block_size, layout.dims[k]
    blocks = layout.offsets[k] + indices
    if method == "dense":
        inverse = np.linalg.inv(gathered_matrix(layout.pattern, diag, off, np))
        rows = blocks[:, None] * D + np.arange(d)[None, :]
        result = inverse[rows[:, :, None], rows[:, None, :]]
    else:
        plan = layout.plan()
        factors = plan.factor(diag, off)
        result = np.empty((len(indices), d, d))
        for m, block in enumerate(blocks):
            for c in range(d):
                rhs = np.zeros((layout.pattern.num_blocks, D))
                rhs[block, c] = 1.0
                result[m, :, c] = plan.solve_factored(factors, rhs)[block, :d]
    result[~layout.free[k][indices]] = 0.0
    return result


def padded_blocks(layout, diag, off):
    """`(diag (N, D, D), off (P, D, D))` in NumPy: the blocks per kind of `layout` on its padded
    pattern, identity on the diagonal padding and zeros elsewhere (`_linear.to_padded`, which
    the solve loop runs inside JAX)."""
    D = layout.block_size
    diag = [np.asarray(block) for block in diag]
    padded_diag = np.tile(np.eye(D, dtype=diag[0].dtype), (layout.pattern.num_blocks, 1, 1))
    for k, block in enumerate(diag):
        d = layout.dims[k]
        padded_diag[layout.offsets[k] : layout.offsets[k + 1], :d, :d] = block
    padded_off = np.zeros((layout.pattern.num_pairs, D, D), diag[0].dtype)
    for key, block in zip(layout.pairs, off):
        da, db = layout.dims[key[0]], layout.dims[key[1]]
        padded_off[layout.slots[key], :da, :db] = np.asarray(block)
    return padded_diag, padded_off
