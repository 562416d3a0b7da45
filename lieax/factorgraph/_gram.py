r"""Grouped Gram sums $G_s = \sum_{i \in s} X_{u_i}^\top Y_{v_i}$ as batched products of chunks.

The Schur complement of bundle adjustment sums $B_{cp} H_{pp}^{-1} B_{c'p}^\top$ over the
points $p$ two cameras share, and the normal equations sum $A_i^\top A_i$ over each camera's
observations: many small products into few slots. One small product per term followed by a
scatter (a segment sum) is slow on a CPU (a call per 9×3 product and a scattered update per
term). Instead, `gram_plan` sorts the terms by slot on the host and cuts each slot's run into
chunks of `C` terms (the last one padded with a zero row), and `gram_sum` computes, per chunk,
$[X_{u_1}; \dots; X_{u_C}]^\top [Y_{v_1}; \dots; Y_{v_C}]$, one `(a, Ck) × (Ck, b)` product,
then adds the few chunks of each slot (a sorted segment sum). The sums are those of the Schur
complement and normal equations of Triggs et al. ("Bundle adjustment — a modern synthesis",
2000, Sec. 6.1); Ceres' `SchurEliminator` also works by chunks, there the rows of one point.
"""

import dataclasses

import jax.numpy as jnp
import numpy as np
from jax import lax

from ._segments import segment_sum

# longest contraction `small_matmul` and the like write out as elementwise sums
_UNROLLED = 8

# gathered entries per operand and block of chunks (`gram_sum`)
_BLOCK_ENTRIES = 1 << 17


def small_matmul(a, b):
    r"""`a @ b` for batches of small blocks `(..., m, k)` and `(..., k, n)`, written out as the
    $k$ broadcast products $\sum_i a_{:, i} b_{i, :}$: one fused elementwise loop, where XLA CPU
    makes a batched product of tiny blocks one small call per block (the $3 \times 3$ by
    $3 \times 9$ products $H_{pp}^{-1} B^\top$ of Trafalgar-138's 166k observations took about
    half the time elementwise). Contractions longer than `_UNROLLED` stay products."""
    if a.shape[-1] > _UNROLLED:
        return jnp.matmul(a, b)
    out = a[..., :, 0:1] * b[..., 0:1, :]
    for i in range(1, a.shape[-1]):
        out = out + a[..., :, i : i + 1] * b[..., i : i + 1, :]
    return out


def small_matvec(a, x):
    """`a @ x[..., None]` for batches of small blocks `a` `(..., m, k)` and vectors `x`
    `(..., k)`, elementwise as `small_matmul`."""
    if a.shape[-1] > _UNROLLED:
        return (a @ x[..., None])[..., 0]
    out = a[..., 0] * x[..., 0:1]
    for i in range(1, a.shape[-1]):
        out = out + a[..., i] * x[..., i : i + 1]
    return out


def small_tmatmul(a, b):
    """`swapaxes(a, -1, -2) @ b` for `a` `(..., k, m)`, `b` `(..., k, n)` (the $A^\top B$ of
    Jacobian blocks), elementwise as `small_matmul`, without the transposed copy of `a`."""
    if a.shape[-2] > _UNROLLED:
        return jnp.swapaxes(a, -1, -2) @ b
    out = a[..., 0, :, None] * b[..., 0, None, :]
    for i in range(1, a.shape[-2]):
        out = out + a[..., i, :, None] * b[..., i, None, :]
    return out


@dataclasses.dataclass(frozen=True)
class GramPlan:
    """Chunks of terms: `left[c]`, `right[c]` `(chunks, C)` the rows of $X$ and $Y$ of chunk
    `c` (the padding points at a zero row appended to each), `segment[c]` its slot (sorted),
    `count` the slots."""

    left: np.ndarray
    right: np.ndarray
    segment: np.ndarray
    count: int


def chunk_size(terms, count, largest=64):
    """A chunk length for `terms` terms into `count` slots: the power of two nearest below the
    mean run length, at most `largest` (short runs waste less padding, long ones make fewer and
    larger products)."""
    mean = terms / max(count, 1)
    return int(min(largest, 2 ** max(0, int(np.floor(np.log2(max(mean, 1)))))))


def gram_plan(u, v, segment, count, pad_left, pad_right, chunk=None):
    r"""The `GramPlan` of terms $X_{u_i}^\top Y_{v_i}$ into slots `segment[i]` of `count`;
    `pad_left`, `pad_right`: the index of the zero row appended to $X$ and to $Y$ (their row
    counts)."""
    u, v, segment = (np.asarray(a, dtype=np.int64) for a in (u, v, segment))
    if chunk is None:
        chunk = chunk_size(len(u), count)
    order = np.argsort(segment, kind="stable")
    runs = np.bincount(segment, minlength=count)
    chunks = -(-runs // chunk)
    chunk_segment = np.repeat(np.arange(count), chunks)
    # first term of each chunk: its slot's first term plus `chunk` per earlier chunk of the slot
    first_chunk = np.concatenate([[0], np.cumsum(chunks)[:-1]])
    first_term = np.concatenate([[0], np.cumsum(runs)[:-1]])
    within = np.arange(len(chunk_segment)) - first_chunk[chunk_segment]
    position = (first_term[chunk_segment] + within * chunk)[:, None] + np.arange(chunk)
    valid = position < (first_term + runs)[chunk_segment][:, None]
    position = np.where(valid, position, 0)
    left = np.where(valid, u[order][position], pad_left)
    right = np.where(valid, v[order][position], pad_right)
    return GramPlan(left.astype(np.int32), right.astype(np.int32), chunk_segment, int(count))


def gram_sum(plan, x, y):
    r"""$G_s = \sum_{i \in s} X_{u_i}^\top Y_{v_i}$, `(count, a, b)`, for `x` `(m, k, a)` and
    `y` `(m', k, b)` (see the module docstring). The chunks go through a `lax.scan` in blocks of
    about `_BLOCK_ENTRIES` gathered entries per operand: XLA CPU's batched product of two
    computed operands slows down several times once they outgrow the cache (5,058 products of
    48×9 blocks, ladybug-49's fill: 73 ms in one product, 5-15 ms for the same work in blocks
    of 250 to 2,500)."""
    k, a, b = x.shape[1], x.shape[2], y.shape[2]
    x = jnp.concatenate([x, jnp.zeros((1, k, a), x.dtype)])
    y = jnp.concatenate([y, jnp.zeros((1, k, b), y.dtype)])
    n, chunk = plan.left.shape
    block = max(1, min(n, _BLOCK_ENTRIES // (chunk * k * max(a, b))))
    steps = -(-n // block)
    pad = ((0, steps * block - n), (0, 0))
    left = np.pad(plan.left, pad, constant_values=x.shape[0] - 1).reshape(steps, block, chunk)
    right = np.pad(plan.right, pad, constant_values=y.shape[0] - 1).reshape(steps, block, chunk)

    def products(_, rows):
        u, v = rows
        xu = x[u].reshape(block, chunk * k, a)
        yv = y[v].reshape(block, chunk * k, b)
        return None, jnp.einsum("nka,nkb->nab", xu, yv)

    _, blocks = lax.scan(products, None, (left, right))
    blocks = blocks.reshape(steps * block, a, b)[:n]
    return segment_sum(blocks, plan.segment, plan.count)
