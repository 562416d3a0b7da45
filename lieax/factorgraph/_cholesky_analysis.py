r"""The symbolic analysis of the multifrontal block Cholesky (`_multifrontal.CholeskyPlan`), in
NumPy, once per graph and elimination order: the elimination tree and the row structures of the
block columns of $L$, supernodes by relaxed amalgamation (CHOLMOD's, in blocks), and a schedule
that groups fronts of the same height in the tree and similar size into batches, chosen by a cost
model of one batch on the host (`_batch_seconds`). Duff and Reid's multifrontal method; Liu, "The
multifrontal method for sparse matrix solution", SIAM Review 1992.
"""

import dataclasses

import numpy as np


def _elimination_structure(n, rows, cols, position):
    """Row structures of the block columns of $L$ (in elimination positions) and the tree."""
    a, b = position[rows], position[cols]
    low, high = np.minimum(a, b), np.maximum(a, b)
    higher = [[] for _ in range(n)]
    for x, y in zip(low.tolist(), high.tolist()):
        higher[x].append(y)
    children = [[] for _ in range(n)]
    structure = [None] * n
    parent = np.full(n, -1, dtype=np.int64)
    for j in range(n):
        s = set(higher[j])
        for c in children[j]:
            s |= structure[c]
        s.discard(j)
        structure[j] = s
        if s:
            p = min(s)
            parent[j] = p
            children[p].append(j)
    return structure, parent


def _amalgamate(n, structure, parent, max_pivots, zero_fraction):
    """Supernodes: a child front merges into its parent when it adds no zeros, when the merged
    front has at most `max_pivots[0]` pivot blocks, or when the added zeros are below
    `zero_fraction[k]` of the merged front's pivot columns for merged sizes up to
    `max_pivots[k]` (CHOLMOD's relaxed amalgamation, in blocks)."""
    pivots = {j: [j] for j in range(n)}
    update = {j: structure[j] for j in range(n)}
    zeros = dict.fromkeys(range(n), 0)
    children = {j: [] for j in range(n)}
    for j in range(n):
        if parent[j] >= 0:
            children[parent[j]].append(j)
    for f in range(n):
        for c in list(children[f]):
            pc, pf, uf = len(pivots[c]), len(pivots[f]), len(update[f])
            added = pc * (pf + uf - len(update[c])) + zeros[c] + zeros[f]
            k = pc + pf
            total = k * (k + 1) / 2 + k * uf
            fraction = added / total
            merge = (
                added == 0
                or k <= max_pivots[0]
                or any(
                    k <= limit and fraction < tol
                    for limit, tol in zip(max_pivots[1:], zero_fraction)
                )
            )
            if merge:
                pivots[f] = pivots[c] + pivots[f]
                zeros[f] = added
                children[f].remove(c)
                children[f].extend(children[c])
                del pivots[c], update[c], children[c], zeros[c]
    return pivots, update, children


@dataclasses.dataclass(frozen=True)
class _Symbolic:
    """The fronts of one elimination order and their batches (`CholeskyPlan.analyze`)."""

    order: np.ndarray
    position: np.ndarray
    pivots: list  # per front, its pivot blocks (elimination positions, sorted)
    updates: list  # per front, its update blocks
    children: list  # per front, its child fronts
    height: np.ndarray  # per front, its height in the tree
    batches: list  # per batch, its fronts
    seconds: float  # modelled time of one factorization (`_batch_seconds`)

    @classmethod
    def of_order(cls, pattern, order, max_pivots, zero_fraction):
        n, d = pattern.num_blocks, pattern.block_size
        position = np.empty(n, dtype=np.int64)
        position[order] = np.arange(n)
        structure, parent = _elimination_structure(n, pattern.rows, pattern.cols, position)
        pivots, update, children = _amalgamate(n, structure, parent, max_pivots, zero_fraction)
        # fronts in elimination (topological) order; rows sorted by elimination position
        fronts = sorted(pivots, key=lambda f: max(pivots[f]))
        front_index = {f: k for k, f in enumerate(fronts)}
        piv = [np.array(sorted(pivots[f]), dtype=np.int64) for f in fronts]
        upd = [np.array(sorted(update[f]), dtype=np.int64) for f in fronts]
        kids = [[front_index[c] for c in children[f]] for f in fronts]
        height = np.zeros(len(fronts), dtype=np.int64)
        for k in range(len(fronts)):
            height[k] = 1 + max((height[c] for c in kids[k]), default=-1)
        # batches: per height, an optimal split of the fronts sorted by size (see `_split_level`)
        members_of, seconds = [], 0.0
        for level in range(int(height.max()) + 1):
            members = np.flatnonzero(height == level)
            sizes = [(len(piv[k]), len(upd[k])) for k in members]
            split = _split_level(members, sizes, d)
            members_of.extend(split)
            seconds += sum(
                _batch_seconds(len(m), max(len(piv[k]) for k in m), max(len(upd[k]) for k in m), d)
                for m in split
            )
        return cls(order, position, piv, upd, kids, height, members_of, seconds)

    @property
    def batch_share(self):
        """The share of the modelled time that is the batches' fixed cost."""
        return len(self.batches) * _BATCH_SECONDS / self.seconds


def _plan_stats(pattern, symbolic, ordering):
    """`CholeskyPlan.stats`: the ordering, fronts, batches, tree height, multiply-adds of one
    factorization with and without the batches' padding, stored blocks of $L$."""
    d, piv, upd = pattern.block_size, symbolic.pivots, symbolic.updates
    padded = sum(
        len(m) * _front_work(max(len(piv[k]) for k in m), max(len(upd[k]) for k in m))
        for m in symbolic.batches
    )
    work = sum(_front_work(len(a), len(b)) for a, b in zip(piv, upd))
    return {
        "ordering": ordering,
        "fronts": len(piv),
        "batches": len(symbolic.batches),
        "height": int(symbolic.height.max()) + 1,
        "flops": float(padded * d**3),
        "flops_unpadded": float(work * d**3),
        "nnz_blocks": int(
            sum(len(a) * (len(a) + 1) // 2 + len(a) * len(b) for a, b in zip(piv, upd))
        ),
    }


# cost model of one batch on the host, in seconds: a fixed cost for its dozen numpy calls, a cost
# per stored scalar of its padded fronts (assembly, layout change, copies) and per multiply-add
_BATCH_SECONDS = 300e-6
_ENTRY_SECONDS = 6e-9
_FLOP_SECONDS = 0.5e-9


def _batch_seconds(count, pivots, updates, d):
    size = (pivots + updates) * d
    return _BATCH_SECONDS + count * (
        size * size * _ENTRY_SECONDS + _front_work(pivots, updates) * d**3 * _FLOP_SECONDS
    )


def _split_level(members, sizes, d):
    """Fronts of one height (`members`, with `(pivots, updates)` `sizes`) split into batches of
    least total modelled time (`_batch_seconds`): the distinct sizes sorted by total size, and a
    dynamic program over contiguous runs of them (each batch is padded to its largest pivots and
    updates)."""
    by_shape = {}
    for k, shape in zip(members.tolist(), sizes):
        by_shape.setdefault(shape, []).append(k)
    shapes = sorted(by_shape, key=lambda s: (s[0] + s[1], s[0]))
    counts = [len(by_shape[s]) for s in shapes]
    m = len(shapes)
    best = [0.0] + [np.inf] * m
    cut = [0] * (m + 1)
    for end in range(1, m + 1):
        big_p = big_u = count = 0
        for start in range(end - 1, -1, -1):
            big_p = max(big_p, shapes[start][0])
            big_u = max(big_u, shapes[start][1])
            count += counts[start]
            cost = best[start] + _batch_seconds(count, big_p, big_u, d)
            if cost < best[end]:
                best[end], cut[end] = cost, start
    batches, end = [], m
    while end > 0:
        start = cut[end]
        batches.append([k for s in shapes[start:end] for k in by_shape[s]])
        end = start
    return batches[::-1]


def _front_work(pivots, updates):
    """Multiply-adds (in units of d³) of a front: Cholesky, triangular solve, Schur update."""
    return pivots**3 / 3 + pivots**2 * updates + pivots * updates**2 / 2 + 1
