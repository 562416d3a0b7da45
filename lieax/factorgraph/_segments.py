r"""Segment sums $S_s = \sum_{i : \mathrm{index}_i = s} t_i$ over indices known on the host, as
one gather where the slots hold similar numbers of terms.

The normal equations and the Schur complement sum many small blocks into fixed slots (a pose's
diagonal block from its edges, a keyframe's from its factors, the blocks of each pair of
variables). XLA's CPU backend runs a scatter (`jax.ops.segment_sum`, `.at[].add`) as a serial
loop of a few kernels per term, which costs most where the whole solve is short: on tinyGrid3D
(9 poses, 22 diagonal terms per linearization) the gather made `lieax.graph.optimize` 8-9% faster
(2026-12-05, both in one process, 21 rounds). Where the indices are host arrays (a structure's,
built once) and no slot holds more than $1 + 2m/\mathrm{count}$ of the $m$ terms, `segment_sum`
gathers the terms by a `(count, width)` table of their positions, padded with a zero term, and
sums its rows: the table holds at most about twice the terms. Otherwise it scatters: where a few
slots collect many terms (the points of bundle adjustment that many cameras see), tables of the
overflow summed level by level measured slower than the scatter (Ladybug-49's points: 194-272 ms
against 172-183 ms a solve). The terms are summed in another order than the scatter's, which
changes results by rounding only.
"""

import jax
import jax.numpy as jnp
import numpy as np


def segment_sum(terms, indices, count):
    """`(count, ...)`: the sum of the rows of `terms` `(m, ...)` per segment `indices` `(m,)` in
    `0..count-1` (empty segments zero): one gather for host (numpy) `indices` whose segments hold
    similar numbers of terms, else `jax.ops.segment_sum` (see the module docstring)."""
    if isinstance(indices, np.ndarray) and len(indices):
        degree = np.bincount(indices, minlength=count)
        width = int(degree.max())
        if count * width <= 2 * len(indices) + count:
            order = np.argsort(indices, kind="stable")
            rank = np.arange(len(indices)) - (np.cumsum(degree) - degree)[indices[order]]
            table = np.full((count, width), len(indices), np.int32)
            table[indices[order], rank] = order
            padded = jnp.concatenate([terms, jnp.zeros((1, *terms.shape[1:]), terms.dtype)])
            return padded[table].sum(axis=1)
    ordered = isinstance(indices, np.ndarray) and bool(np.all(indices[1:] >= indices[:-1]))
    return jax.ops.segment_sum(terms, indices, count, indices_are_sorted=ordered)


__all__ = ["segment_sum"]
