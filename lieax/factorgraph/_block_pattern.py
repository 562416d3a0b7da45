r"""The pattern of a symmetric block-sparse matrix (the normal equations of `lieax.factorgraph`)
and what is computed from the blocks alone: the product $H x$ and the dense matrix.

The matrix is symmetric with `n` diagonal blocks of size `d` (one per pose or variable) and one
off-diagonal block per pair joined by a factor: `diag` `(n, d, d)` holds $H_{aa}$, `off` `(p, d, d)`
holds $H_{ab}$ for the pairs `rows[k] = a < b = cols[k]` of a fixed `BlockPattern`
($H_{ba} = H_{ab}^\top$). Assembly is a segment sum over edges into these fixed slots, so
nothing is rebuilt from one iteration to the next. Its solvers: `_multifrontal` (sparse
Cholesky), `_dense_solve`, `_pcg`.
"""

import dataclasses

import jax.numpy as jnp
import numpy as np


@dataclasses.dataclass(frozen=True)
class BlockPattern:
    """The sparsity of a symmetric block matrix: `num_blocks` diagonal blocks of size
    `block_size` and off-diagonal blocks at `(rows[k], cols[k])`, `rows < cols`, sorted, unique."""

    num_blocks: int
    block_size: int
    rows: np.ndarray
    cols: np.ndarray

    @property
    def num_pairs(self) -> int:
        return int(self.rows.shape[0])

    @classmethod
    def from_edges(cls, num_blocks, block_size, i, j):
        """The pattern of edges `(i, j)` (any order, duplicates allowed) and, per edge, the index
        of its pair and whether it is flipped (`i > j`, so its block $H_{ij}$ is stored transposed)."""
        i, j = np.asarray(i, dtype=np.int64), np.asarray(j, dtype=np.int64)
        low, high = np.minimum(i, j), np.maximum(i, j)
        keys = low * num_blocks + high
        unique, pair = np.unique(keys, return_inverse=True)
        pattern = cls(num_blocks, block_size, unique // num_blocks, unique % num_blocks)
        return pattern, pair.reshape(-1), i > j


def block_matvec(pattern, diag, off, x):
    """$H x$ for `x` `(n, d)`."""
    rows, cols = jnp.asarray(pattern.rows), jnp.asarray(pattern.cols)
    y = jnp.einsum("nab,nb->na", diag, x)
    y = y.at[rows].add(jnp.einsum("kab,kb->ka", off, x[cols]))
    return y.at[cols].add(jnp.einsum("kba,kb->ka", off, x[rows]))


def dense_matrix(pattern, diag, off):
    """The dense `(n d, n d)` matrix (tests, and the dense solve of a bucketed graph). The blocks
    are added into place, so that a padded pair of zero blocks (a bucketed graph's, which may
    repeat a pair or name a diagonal block) adds nothing."""
    n, d = pattern.num_blocks, pattern.block_size
    blocks = jnp.zeros((n, n, d, d), diag.dtype)
    blocks = blocks.at[jnp.arange(n), jnp.arange(n)].set(diag)
    blocks = blocks.at[pattern.rows, pattern.cols].add(off)
    blocks = blocks.at[pattern.cols, pattern.rows].add(jnp.swapaxes(off, -1, -2))
    return blocks.transpose(0, 2, 1, 3).reshape(n * d, n * d)


__all__ = ["BlockPattern", "block_matvec", "dense_matrix"]
