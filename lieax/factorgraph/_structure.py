r"""The structure of a factor graph, analysed once on the host in numpy (nothing is traced).

Every variable instance is one block of the normal equations $H\,\delta = -g$, of its kind's
tangent dimension $d_k$. A factor over instances $(a, b, \dots)$ adds to the diagonal blocks
$H_{aa}$ and to the off-diagonal blocks $H_{ab}$ of every pair of its arguments, so the block
pattern of $H = J^\top W J$ is the union of those pairs. A `Layout` keeps it per kind:
diagonal blocks `(n_k, d_k, d_k)` per variable kind and off-diagonal blocks `(p, d_a, d_b)`
per pair of kinds `(a, b)`, `a <= b` in the order of the graph's variables (within one kind
`rows < cols`, as `lieax.graph.BlockPattern`). For the sparse solvers the blocks are laid into
one uniform `BlockPattern` of block size $D = \max_k d_k$, each block padded with the identity
on its diagonal padding and zeros elsewhere, so that the padded unknowns solve to zero and the
multifrontal `CholeskyPlan` of `lieax.graph` (one block size) serves mixed sizes.

`schur_layout` finds, for a kind `e` whose instances share no factor, the pattern of the
reduced system $S = H_{rr} - H_{re} H_{ee}^{-1} H_{er}$ over the other kinds: two instances are
linked in $S$ when they are linked in $H$ or share an eliminated instance (cameras that see a
common point in bundle adjustment; Triggs et al. 2000, Sec. 6.1).
"""

import concurrent.futures
import dataclasses
import hashlib
import threading
from collections.abc import Sequence

import numpy as np
from jax.typing import ArrayLike

from ._block_pattern import BlockPattern
from ._gram import gram_plan
from ._multifrontal import CholeskyPlan, cholesky_solve


@dataclasses.dataclass
class Layout:
    """Block pattern over variable kinds (see the module docstring).

    `dims[k]`, `counts[k]`: tangent dimension and instances of kind `k`; `pairs[(a, b)]`:
    `(rows, cols)` instance indices of the off-diagonal blocks between kinds `a <= b`;
    `free[k]`: bool `(n_k,)`, False for fixed instances."""

    dims: tuple
    counts: tuple
    pairs: dict
    free: tuple

    def __post_init__(self):
        self.offsets = np.concatenate([[0], np.cumsum(self.counts)]).astype(np.int64)
        self.block_size = max(self.dims)
        self._plan = None
        self._analysis = None
        self.sparse_cost = None  # `(seconds, multiply-adds, fill)`, `_elimination`
        self._lock = threading.Lock()
        n = int(self.offsets[-1])
        items = self.pairs.items()
        if self.pairs:
            global_rows = np.concatenate([self.offsets[a] + r for (a, _), (r, _) in items])
            global_cols = np.concatenate([self.offsets[b] + c for (_, b), (_, c) in items])
        else:
            global_rows = global_cols = np.zeros(0, np.int64)
        self.pattern, slots, _ = BlockPattern.from_edges(
            n, self.block_size, global_rows, global_cols
        )
        self.slots, start = {}, 0
        for key, (r, _) in self.pairs.items():
            self.slots[key] = slots[start : start + len(r)]
            start += len(r)
        self.pair_free = {
            (a, b): self.free[a][r] & self.free[b][c] for (a, b), (r, c) in self.pairs.items()
        }

    @property
    def num_unknowns(self):
        return int(np.dot(self.dims, self.counts))

    @property
    def padded_unknowns(self):
        return int(self.offsets[-1]) * self.block_size

    def start_plan(self):
        """Begin the `CholeskyPlan`'s analysis in a background thread, once: NumPy and SciPy
        work on the host that overlaps the tracing and the XLA compilation of the loop that will
        call it (XLA releases the GIL while it compiles; the analysis of the 10k-pose graphs of
        `benchmarks/factorgraph.py` took 1-3 s, a third to half of their compilation)."""
        with self._lock:
            if self._analysis is None:
                self._analysis = _ANALYSES.submit(CholeskyPlan.analyze, self.pattern)

    def plan(self):
        """The `CholeskyPlan` of the padded pattern (analysed on first use, or waited for when
        `start_plan` began it; its errors are raised here)."""
        if self._plan is None:
            self.start_plan()
            self._plan = self._analysis.result()
        return self._plan

    def cholesky_solve(self, diag, off, rhs):
        """$H^{-1}$ `rhs` on the padded pattern by its `CholeskyPlan` (`start_plan` may still be
        analysing it: `cholesky_solve` waits when it needs it)."""
        return cholesky_solve(self.plan, diag, off, rhs, pattern=self.pattern)


# one host thread for the Cholesky analyses (`Layout.start_plan`), made on first use
_ANALYSES = concurrent.futures.ThreadPoolExecutor(1, thread_name_prefix="lieax-analysis")


def pair_slots(pairs, a, b, ia, ib):
    """Slots in `pairs[(a, b)]` of the blocks between instances `ia` of kind `a` and `ib` of `b`
    (`a <= b`; within one kind the caller orders `ia < ib`)."""
    rows, cols = pairs[(a, b)]
    count = max(int(cols.max(initial=0)), int(ib.max(initial=0))) + 1
    keys = rows * count + cols
    return np.searchsorted(keys, ia * count + ib)


def unique_pairs(ia, ib):
    """Sorted unique `(rows, cols)` of the pairs `(ia, ib)`."""
    if len(ia) == 0:
        return np.zeros(0, np.int64), np.zeros(0, np.int64)
    count = int(max(ia.max(), ib.max())) + 1
    keys = np.unique(ia * count + ib)
    return keys // count, keys % count


@dataclasses.dataclass(frozen=True)
class FactorPlan:
    r"""Where one factor kind's blocks go: `kinds[s]` of each argument, `indices[s]`, and per pair
    of arguments `(s, t, key, slots, flipped)`: the kind pair `key`, the slot of each instance's
    block and whether $J_s^\top J_t$ is stored transposed (a bool per instance within one kind,
    a Python bool across kinds); `grams[s]` the `GramPlan` summing argument `s`'s diagonal
    blocks and gradients where its instances collect long runs of terms, else `None` (a segment
    sum); `valid`, for a bucketed graph (`_buckets`), a bool per instance, False for the padding
    (masked out of the cost and the normal equations), else `None`."""

    kinds: tuple
    indices: tuple
    couplings: tuple
    grams: tuple
    valid: object = None


def analyze(variables, factors, unary=None):
    """`(layout, factor_plans)`; `ValueError`s for bad indices, repeated arguments and, unless
    `unary` is `None`, unanchored components (`unary[j]`: the directions each instance of the
    unary factor kind `j` constrains, `check_anchored`)."""
    kind_of = {id(v): k for k, v in enumerate(variables)}
    counts = tuple(v.count for v in variables)
    links = {}
    per_factor = []
    for f in factors:
        kinds = tuple(kind_of[id(v)] for v in f.vars)
        for s, (k, index) in enumerate(zip(kinds, f.indices)):
            bad = (index < 0) | (index >= counts[k])
            if np.any(bad):
                first = int(np.argmax(bad))
                raise ValueError(
                    f"factor kind {f.name!r}: argument {s} index {int(index[first])} (instance "
                    f"{first}) is out of range for variable kind {variables[k].name!r} with "
                    f"{counts[k]} instances."
                )
        pairs = []
        for s in range(len(kinds)):
            for t in range(s + 1, len(kinds)):
                ks, kt = kinds[s], kinds[t]
                i_s, i_t = f.indices[s], f.indices[t]
                if ks == kt:
                    same = i_s == i_t
                    if np.any(same):
                        first = int(np.argmax(same))
                        raise ValueError(
                            f"factor kind {f.name!r}: instance {first} uses variable "
                            f"{variables[ks].name!r}[{int(i_s[first])}] for arguments {s} and {t}."
                        )
                    low, high = np.minimum(i_s, i_t), np.maximum(i_s, i_t)
                    key, ia, ib, flipped = (ks, ks), low, high, i_s > i_t
                elif ks < kt:
                    key, ia, ib, flipped = (ks, kt), i_s, i_t, False
                else:
                    key, ia, ib, flipped = (kt, ks), i_t, i_s, True
                links.setdefault(key, []).append((ia, ib))
                pairs.append((s, t, key, ia, ib, flipped))
        per_factor.append((kinds, pairs))
    pair_lists = {
        key: unique_pairs(np.concatenate([a for a, _ in v]), np.concatenate([b for _, b in v]))
        for key, v in sorted(links.items())
    }
    free = []
    for v in variables:
        mask = np.ones(v.count, dtype=bool)
        mask[v.fixed] = False
        free.append(mask)
    layout = Layout(tuple(v.tangent_dim for v in variables), counts, pair_lists, tuple(free))
    plans = []
    for f, (kinds, pairs) in zip(factors, per_factor):
        couplings = tuple(
            (s, t, key, pair_slots(pair_lists, *key, ia, ib), flipped)
            for s, t, key, ia, ib, flipped in pairs
        )
        grams = tuple(_gram_or_none(index, counts[k]) for k, index in zip(kinds, f.indices))
        plans.append(FactorPlan(kinds, f.indices, couplings, grams))
    if unary is not None:
        check_anchored(variables, factors, layout, plans, unary)
    return layout, plans


# mean terms per slot from which a `GramPlan` beats a segment sum (XLA CPU, ladybug-49's
# normal equations: 31,843 camera blocks into 49 cameras, segment sum 90 ms, chunked 3-11 ms;
# about 4 terms per point, segment sum 0.5 ms, chunked 4-6 ms)
_GRAM_MIN_RUN = 16


def _gram_or_none(index, count):
    """The `GramPlan` of the terms `index` into `count` slots, or `None` for short runs."""
    if len(index) < _GRAM_MIN_RUN * count:
        return None
    terms = np.arange(len(index))
    return gram_plan(terms, terms, index, count, len(index), len(index))


def check_anchored(variables, factors, layout, plans, unary):
    """`ValueError` unless every connected component of the graph (instances linked by
    factors) holds a fixed instance or unary factors that constrain, together, at least as many
    directions as the largest tangent dimension among its variables (`unary[j]`: per instance
    of the unary kind `j`, the rank of its square-root information): elsewhere relative factors
    leave a free gauge (the component can move as a whole). The count is necessary, not
    sufficient (two position priors leave the rotation about the line through them free): a
    prior with zero rotation precision on the first pose fixes no rotation, GPS positions on
    two poses of a 2D chain fix its gauge."""
    n = int(layout.offsets[-1])
    count, labels = connected_components(n, layout.pattern.rows, layout.pattern.cols)
    anchored = np.zeros(count, dtype=bool)
    for k, v in enumerate(variables):
        anchored[labels[layout.offsets[k] + v.fixed]] = True
    constrained = np.zeros(count, np.int64)
    for j, ranks in unary.items():
        node = layout.offsets[plans[j].kinds[0]] + plans[j].indices[0]
        np.add.at(constrained, labels[node], ranks)
    dims = np.repeat(layout.dims, layout.counts)
    needed = np.zeros(count, np.int64)
    np.maximum.at(needed, labels, dims)
    anchored |= constrained >= needed
    if not anchored.all():
        free = np.flatnonzero(~anchored)
        sizes = np.bincount(labels, minlength=count)
        described = []
        for c in free[:3]:
            first = int(np.argmax(labels == c))
            k = int(np.searchsorted(layout.offsets, first, side="right") - 1)
            described.append(
                f"{sizes[c]} variables from {variables[k].name!r}[{first - layout.offsets[k]}], "
                f"priors constraining {constrained[c]} of {needed[c]} directions"
            )
        raise ValueError(
            f"{len(free)} of the graph's {count} connected components have no fixed variable "
            f"and no unary (prior) factors that constrain all its directions "
            f"({'; '.join(described)}{', ...' if len(free) > 3 else ''}): their gauge is free "
            "and the normal equations are singular. Fix a variable (Var(..., fixed=...)), add "
            "a prior factor, or pass check_gauge=False to rely on the damping."
        )


def connected_components(
    n: int, rows: ArrayLike | Sequence[int], cols: ArrayLike | Sequence[int]
) -> tuple[int, np.ndarray]:
    """`(count, labels)` of the undirected graph of `n` nodes and edges `(rows[e], cols[e])`,
    labelled as `scipy.sparse.csgraph.connected_components` does (component `c` is the one of
    the `c`-th smallest node that starts a component), in NumPy without importing SciPy's
    csgraph (0.5-2 s on a first call).

    Hooking and pointer jumping (Shiloach and Vishkin, "An O(log n) parallel connectivity
    algorithm", 1982): every node points to a smaller one of its component or to itself; each
    round hooks the larger root of every edge whose ends have different roots onto the
    smaller, then jumps pointers until each points at its root. Roots only decrease, so it
    ends; a path of `n` nodes takes one round and `log2 n` jumps."""
    parent = np.arange(n)
    rows, cols = np.asarray(rows, np.int64), np.asarray(cols, np.int64)
    while True:
        a, b = parent[rows], parent[cols]
        split = a != b
        if not split.any():
            break
        np.minimum.at(parent, np.maximum(a[split], b[split]), np.minimum(a[split], b[split]))
        while True:
            jumped = parent[parent]
            if np.array_equal(jumped, parent):
                break
            parent = jumped
    roots, labels = np.unique(parent, return_inverse=True)
    return len(roots), labels.reshape(n)


@dataclasses.dataclass(frozen=True)
class SchurPlan:
    r"""The elimination of kind `eliminated`: the reduced `layout` over the other kinds
    (`kept[j]` = original kind of reduced kind `j`); per kept kind `r` linked to it,
    `links[r] = (key, slots, inst, point, transposed)` (blocks of pair `key` between instances
    `inst` of `r` and `point` of the eliminated kind; `transposed` when stored as `(e, r)`);
    `original[(a, b)] = (reduced key, slots)` for the blocks among kept kinds; `diagonal[r]` the
    `GramPlan` of the products $B_u H_{pp}^{-1} B_u^\top$ (and $B_u H_{pp}^{-1} b_p$) into the
    diagonal blocks of kind `r`, `fill` a list of `(r1, r2, reduced key, plan)`: the `GramPlan`
    of the products $B_u H_{pp}^{-1} B_v^\top$ (`u` a link of `r1`, `v` of `r2`) into the blocks
    of the reduced key."""

    eliminated: int
    kept: tuple
    layout: Layout
    links: dict
    original: dict
    diagonal: dict
    fill: tuple


def schur_layout(layout, e, names, reduced=None):
    """The `SchurPlan` eliminating kind `e` (see the module docstring); `reduced`, the
    `reduced_layout` of `e` when it is at hand (`elimination_cost` builds it)."""
    kept, new, links, pieces, fill_raw = _reduction(layout, e, names)
    if reduced is None:
        reduced = _reduced(layout, kept, pieces)
    pairs = reduced.pairs
    original = {
        (a, b): ((new[a], new[b]), pair_slots(pairs, new[a], new[b], rows, cols))
        for (a, b), (rows, cols) in layout.pairs.items()
        if e not in (a, b)
    }
    diagonal = {}
    for r, (_, _, inst, _, _) in links.items():
        terms = np.arange(len(inst))
        diagonal[r] = gram_plan(terms, terms, inst, reduced.counts[new[r]], len(inst), len(inst))
    fill = []
    for r1, r2, u, v, key, ia, ib in fill_raw:
        slots = pair_slots(pairs, *key, ia, ib)
        pad_u, pad_v = len(links[r1][2]), len(links[r2][2])
        plan = gram_plan(u, v, slots, len(pairs[key][0]), pad_u, pad_v)
        fill.append((r1, r2, key, plan))
    return SchurPlan(e, kept, reduced, links, original, diagonal, tuple(fill))


def reduced_layout(layout, e, names):
    """The `Layout` of the reduced system after eliminating kind `e` (its pattern only, without
    the `SchurPlan`'s Gram plans)."""
    kept, _, _, pieces, _ = _reduction(layout, e, names)
    return _reduced(layout, kept, pieces)


def _reduction(layout, e, names):
    """`(kept, new, links, pieces, fill_raw)` of the elimination of kind `e`: the kept kinds and
    their new indices, the links of each kept kind to `e` (as `SchurPlan.links`), the block
    pairs of the reduced system per reduced key, and per pair of linked kinds the pairs of
    links `(u, v)` of a common eliminated instance with the blocks they fill."""
    if (e, e) in layout.pairs and len(layout.pairs[(e, e)][0]):
        raise ValueError(
            f"cannot eliminate variable kind {names[e]!r}: some of its instances share a factor "
            "(its block of H is not block diagonal)."
        )
    kept = tuple(k for k in range(len(layout.dims)) if k != e)
    new = {k: j for j, k in enumerate(kept)}
    links = {}
    for (a, b), (rows, cols) in layout.pairs.items():
        if b == e:
            links[a] = ((a, b), np.arange(len(rows)), rows, cols, False)
        elif a == e:
            links[b] = ((a, b), np.arange(len(rows)), cols, rows, True)
    pieces = {}
    for (a, b), (rows, cols) in layout.pairs.items():
        if e not in (a, b):
            pieces.setdefault((new[a], new[b]), []).append((rows, cols))
    fill_raw = []
    for r1, (_, _, inst1, point1, _) in links.items():
        for r2, (_, _, inst2, point2, _) in links.items():
            if r1 > r2:
                continue
            order = np.argsort(point2, kind="stable")
            start = np.searchsorted(point2[order], point1, side="left")
            stop = np.searchsorted(point2[order], point1, side="right")
            lengths = stop - start
            u = np.repeat(np.arange(len(point1)), lengths)
            v = order[np.repeat(start, lengths) + _ranges(lengths)]
            if r1 == r2:
                keep = inst1[u] < inst2[v]
                u, v = u[keep], v[keep]
            ia, ib = inst1[u], inst2[v]
            key = (new[r1], new[r2])
            pieces.setdefault(key, []).append((ia, ib))
            fill_raw.append((r1, r2, u, v, key, ia, ib))
    return kept, new, links, pieces, fill_raw


def _reduced(layout, kept, pieces):
    pairs = {
        key: unique_pairs(np.concatenate([a for a, _ in v]), np.concatenate([b for _, b in v]))
        for key, v in sorted(pieces.items())
    }
    return Layout(
        tuple(layout.dims[k] for k in kept),
        tuple(layout.counts[k] for k in kept),
        pairs,
        tuple(layout.free[k] for k in kept),
    )


def _ranges(lengths):
    """`[0..l0-1, 0..l1-1, ...]` for `lengths`."""
    total = int(lengths.sum())
    if total == 0:
        return np.zeros(0, np.int64)
    starts = np.repeat(np.cumsum(lengths) - lengths, lengths)
    return np.arange(total) - starts


def digest(*arrays):
    """A hash of integer arrays (the structure's cache key, as `lieax.graph.optimize` keys its
    compiled problems)."""
    h = hashlib.blake2b(digest_size=16)
    for a in arrays:
        a = np.ascontiguousarray(a)
        h.update(f"{a.dtype.str}{a.shape}".encode())
        h.update(a.tobytes())
    return h.hexdigest()
