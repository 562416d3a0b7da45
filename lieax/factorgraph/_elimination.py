r"""The Schur choice: whether eliminating a variable kind makes a linear solve cheaper.

A kind whose instances share no factor (points in bundle adjustment, landmarks) can be
eliminated (`_linear.schur_solve`); that pays when its instances are seen by few others (a
point by 2-3 cameras: the reduced camera system is small), and costs when they are seen by
many (a landmark seen by most poses links them all: the reduced pose system is dense where
the whole system was a chain with a few long rows, and its factorization is the whole cost).
The model is the multifrontal Cholesky's own (`_cholesky_analysis._batch_seconds`, which chooses its
ordering), in modelled seconds of one solve:

- the sparse block Cholesky of a system padded to block size $D$: per block column $j$ of
  $L$ in minimum degree order, with $c_j$ off-diagonal blocks, a front of $(1 + c_j) D$
  rows: $((1 + c_j) D)^2$ stored scalars at `_ENTRY_SECONDS` and
  $D^3(\tfrac13 + c_j + \tfrac12 c_j^2 + 1)$ multiply-adds (`_front_work`) at
  `_FLOP_SECONDS` (without the batches' fixed cost: the amalgamation and the batching only
  lower it; George and Liu, "Computer solution of large sparse positive definite systems",
  1981, Sec. 2.2);
- the dense Cholesky of $n$ padded unknowns in JAX: $n^3/3$ multiply-adds at
  `_DENSE_FLOP_SECONDS`;
- with elimination, forming $S = H_{rr} - H_{re} H_{ee}^{-1} H_{er}$ and its right-hand side
  too, at `_FLOP_SECONDS`: per eliminated instance $p$ of dimension $d_e$ with links of
  dimensions $d_u$, $d_e^3$ for $H_{pp}^{-1}$, $d_e^2 \sum_u d_u$ for the products
  $H_{pp}^{-1} B_u^\top$ and $d_e \sum_{u \le v} d_u d_v
  = \tfrac12 d_e ((\sum_u d_u)^2 + \sum_u d_u^2)$ for the blocks $B_u H_{pp}^{-1} B_v^\top$
  (Triggs et al., "Bundle adjustment — a modern synthesis", 2000, Sec. 6.1).

`"cg"` and `"auto"` are costed with the factorization `linear_solver="auto"` would pick for that
system: a stand-in for conjugate gradients, whose products grow with the same fill.

Measured (`benchmarks/factorgraph.py`, warm LM solves, one process, a shared machine): 20
cameras and 400 points seen by 2.5 of them, eliminating 16x faster than not; 200 SE2 poses and
10 landmarks each seen by 90% of them, eliminating 13x slower (500 poses, 20 landmarks seen by
35%: 140x slower); the model picks the faster in all three.
"""

import dataclasses

import numpy as np

from ._cholesky_analysis import (
    _ENTRY_SECONDS,
    _FLOP_SECONDS,
    _elimination_structure,
    _front_work,
)
from ._ordering import minimum_degree_order
from ._structure import reduced_layout

# seconds per multiply-add of the dense Cholesky in JAX: half the multifrontal's, as
# `linear_solver="auto"` factors densely up to 800 unknowns when the sparse factor would have half the
# dense multiply-adds (`_graph._DENSE_FILL`); measured 0.33 ns at 180 unknowns (CPU, loaded)
_DENSE_FLOP_SECONDS = 0.5 * _FLOP_SECONDS


@dataclasses.dataclass(frozen=True)
class SolveCost:
    """The modelled cost of one linear solve, in seconds: `formation` (forming the reduced
    system, 0 without elimination) and `factorization` (its factorization by `method`), with
    `flops` (their multiply-adds), `off_blocks` (off-diagonal blocks of the factored system)
    and `fill` (stored blocks of its factor)."""

    formation: float
    factorization: float
    method: str
    flops: float
    off_blocks: int
    fill: int

    @property
    def total(self):
        return self.formation + self.factorization

    def describe(self):
        formed = f"{self.formation * 1e3:.3g} ms forming it, then " if self.formation else ""
        return (
            f"{self.total * 1e3:.3g} ms modelled ({formed}a {self.method} factorization of a "
            f"system with {self.off_blocks} off-diagonal blocks, {self.fill} blocks in its "
            f"factor; {self.flops:.3g} multiply-adds in all)"
        )


def factorization_cost(layout, method):
    """`SolveCost` of factoring `layout`'s padded system by `method` (`"dense"` or
    `"cholesky"`), without elimination; the sparse figures are kept on the layout."""
    n = layout.padded_unknowns
    blocks = int(layout.offsets[-1])
    pairs = layout.pattern.num_pairs
    if method == "dense":
        fill = blocks * (blocks + 1) // 2
        return SolveCost(0.0, dense_cost(n), method, n**3 / 3, pairs, fill)
    if layout.sparse_cost is None:
        d, pattern = layout.block_size, layout.pattern
        order = minimum_degree_order(blocks, pattern.rows, pattern.cols)
        position = np.empty(blocks, dtype=np.int64)
        position[order] = np.arange(blocks)
        structure, _ = _elimination_structure(blocks, pattern.rows, pattern.cols, position)
        counts = np.array([len(s) for s in structure], dtype=np.float64)
        flops = float(np.sum(_front_work(1, counts)) * d**3)
        entries = float(np.sum(((1 + counts) * d) ** 2))
        seconds = flops * _FLOP_SECONDS + entries * _ENTRY_SECONDS
        layout.sparse_cost = (seconds, flops, blocks + int(counts.sum()))
    seconds, flops, fill = layout.sparse_cost
    return SolveCost(0.0, seconds, method, flops, pairs, fill)


def dense_cost(n):
    """The modelled seconds of the dense Cholesky of `n` padded unknowns: $n^3/3$ multiply-adds."""
    return n**3 / 3 * _DENSE_FLOP_SECONDS


def factorization_bound(layout):
    """A lower bound of the modelled seconds of `layout`'s sparse factorization, from its
    pattern alone: every off-diagonal block of $H$ is one of $L$, so the $c_j$ sum to at least
    the pattern's $P$ pairs, and the model's terms, convex in $c_j$, are least at
    $c_j = P/N$ (Jensen's inequality)."""
    n, d = int(layout.offsets[-1]), layout.block_size
    c = layout.pattern.num_pairs / max(n, 1)
    flops = n * float(_front_work(1, c)) * d**3
    return flops * _FLOP_SECONDS + n * ((1 + c) * d) ** 2 * _ENTRY_SECONDS


def reduction_bound(layout, e):
    r"""A lower bound of the modelled seconds of the sparse factorization of the system reduced
    by eliminating kind `e`, from the links alone (without the reduced pattern, which is as
    large as its fill: every pair of poses that see a common landmark). The instances linked to
    one eliminated instance are pairwise linked in $S$, a clique of $c$ blocks; in any
    elimination order the $j$-th of them to go still has the $c - 1 - j$ later ones in its
    column of $L$, so $c_j \ge c - 1 - j$ there, and $c_j \ge 0$ in the other columns. The
    model's terms (`factorization_cost`) grow with $c_j$, so the largest clique's
    $\sum_{m < c}$ of them, and the other columns' terms at $c_j = 0$, bound it from below."""
    kept = [k for k in range(len(layout.dims)) if k != e]
    d = max(layout.dims[k] for k in kept)
    n = int(sum(layout.counts[k] for k in kept))
    links = np.zeros(layout.counts[e], np.int64)  # distinct instances linked to each of e's
    for (a, b), (rows, cols) in layout.pairs.items():
        if e in (a, b) and a != b:
            links += np.bincount(cols if b == e else rows, minlength=layout.counts[e])
    c = np.arange(int(links.max(initial=0)), dtype=np.float64)
    flops = (float(np.sum(_front_work(1, c))) + (n - len(c)) * _front_work(1, 0)) * d**3
    entries = float(np.sum(((1 + c) * d) ** 2)) + (n - len(c)) * d**2
    return flops * _FLOP_SECONDS + entries * _ENTRY_SECONDS


def formation_flops(layout, e):
    """Multiply-adds forming the reduced system when kind `e` of `layout` is eliminated."""
    d_e = layout.dims[e]
    linked = np.zeros(layout.counts[e])  # per eliminated instance: sum of its links' dims
    squares = np.zeros(layout.counts[e])  # ... and of their squares
    for (a, b), (rows, cols) in layout.pairs.items():
        if e in (a, b) and a != b:
            point, other = (cols, a) if b == e else (rows, b)
            links = np.bincount(point, minlength=layout.counts[e])
            linked += links * layout.dims[other]
            squares += links * layout.dims[other] ** 2
    return float(
        np.sum(d_e**3 + d_e**2 * linked + 0.5 * d_e * (linked**2 + squares) * (linked > 0))
    )


def formation_seconds(layout, e):
    """The modelled seconds of forming the reduced system when kind `e` is eliminated (cheap:
    from the link counts, without the reduced pattern)."""
    return formation_flops(layout, e) * _FLOP_SECONDS


def candidates(layout):
    """The kinds that may be eliminated: linked to another kind, their instances sharing no
    factor (empty for a graph of one kind)."""
    if len(layout.dims) < 2:
        return ()
    return tuple(
        k
        for k in range(len(layout.dims))
        if not len(layout.pairs.get((k, k), ((),))[0])
        and any(k in key and key[0] != key[1] for key in layout.pairs)
    )


def elimination_cost(layout, e, names, method_of):
    """`(cost, reduced)`: the `SolveCost` of a solve eliminating kind `e`, its reduced system
    factored by `method_of(reduced)`, and that reduced `Layout`."""
    reduced = reduced_layout(layout, e, names)
    cost = factorization_cost(reduced, method_of(reduced))
    formation = formation_flops(layout, e)
    return dataclasses.replace(
        cost, formation=formation * _FLOP_SECONDS, flops=cost.flops + formation
    ), reduced
