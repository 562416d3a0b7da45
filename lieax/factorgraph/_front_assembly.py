r"""The NumPy path's batches of fronts of the multifrontal Cholesky (`_multifrontal.CholeskyPlan`):
where each front sits in its batch and in the work array, and each batch's assembly, a sparse ±1
matrix that gathers its fronts' pivot columns from the work array (the entries of $H$, the identity
on padded pivots, less the update products of descendants). Built from the symbolic analysis
(`_cholesky_analysis._Symbolic`) once per plan, on first use.
"""

import dataclasses

import numpy as np


@dataclasses.dataclass(frozen=True)
class _Batch:
    """One batch of fronts of the same height in the elimination tree, padded to `pivots` +
    `updates` blocks: the indices of its blocks, where its entries come from, and where its
    update product goes."""

    pivot_index: np.ndarray  # (B, P) block of each pivot slot, n for padding
    update_index: np.ndarray  # (B, U) block of each update slot, n for padding
    assembly: object  # scipy CSR (B S d P, rows of the work array): ±1 entries
    work_offset: int  # first row of this batch's update products in the work array
    targets: np.ndarray  # the distinct update blocks of its fronts (`solve_factored`)
    scatter: object  # None when no block is an update block of two of its fronts, else scipy
    # CSR (targets, B U): 0/1 entries summing the update slots of each target

    @property
    def shape(self):
        return (*self.pivot_index.shape, self.update_index.shape[1])


def _numpy_batches(pattern, symbolic):
    """`(batches, work_rows)`: the NumPy path's batches of the fronts of `symbolic`, with their
    assembly matrices, and the rows of its work array (see `CholeskyPlan`)."""
    assembly = _Assembly(pattern, symbolic)
    _add_blocks_of_h(assembly, pattern, symbolic)
    _add_update_products(assembly, symbolic)
    batches = [
        _batch(assembly, g, members, pattern, symbolic)
        for g, members in enumerate(symbolic.batches)
    ]
    return batches, assembly.work_rows


class _Assembly:
    """The fronts' places, and the entries of each batch's assembly matrix as they are added:
    `where` (front -> (batch, position in it)), `shapes` (per batch `(B, P, U)`: fronts, padded
    pivot and update blocks), `offsets` (per batch, the first row of its update products in the
    work array), `work_rows`, `front_of` (elimination position -> front), and per batch the
    destination rows, source rows and signs added so far (`add`)."""

    def __init__(self, pattern, symbolic):
        n, d, p = pattern.num_blocks, pattern.block_size, pattern.num_pairs
        self.d, self.piv, self.upd = d, symbolic.pivots, symbolic.updates
        members_of = symbolic.batches
        self.where = np.empty((len(self.piv), 2), dtype=np.int64)  # front -> (batch, position)
        self.shapes = []
        self.work_rows = (n + 2 * p + 1) * d  # H's blocks, the identity (padding), update products
        self.offsets = []
        for g, members in enumerate(members_of):
            self.where[members, 0] = g
            self.where[members, 1] = np.arange(len(members))
            bp = max(len(self.piv[k]) for k in members)
            bu = max(len(self.upd[k]) for k in members)
            self.shapes.append((len(members), bp, bu))
            self.offsets.append(self.work_rows)
            self.work_rows += len(members) * bu * d * bu
        self.front_of = np.empty(n, dtype=np.int64)  # elimination position -> front
        for k, a in enumerate(self.piv):
            self.front_of[a] = k
        # every block is d segments (rows of d scalars) of the work array, at base + r * stride
        self.dst = [[] for _ in members_of]
        self.src = [[] for _ in members_of]
        self.sign = [[] for _ in members_of]

    def slots(self, k, positions):
        """Rows of elimination positions in front k's layout [pivots (padded) | updates]."""
        piv, upd = self.piv, self.upd
        bp = self.shapes[self.where[k, 0]][1]
        in_pivots = np.searchsorted(piv[k], positions)
        in_pivots_clipped = np.minimum(in_pivots, len(piv[k]) - 1)
        is_pivot = piv[k][in_pivots_clipped] == positions
        return np.where(is_pivot, in_pivots, bp + np.searchsorted(upd[k], positions))

    def add(self, k, r, c, source_base, source_stride, value=1.0):
        """Blocks (r, c) of front k from the work array, times `value`; only the lower block
        triangle (r >= c) of the pivot columns (c < pivots) is assembled: the factorization
        reads no other block."""
        d, dst, src, sign = self.d, self.dst, self.src, self.sign
        g, b = self.where[k]
        s, bp = self.shapes[g][1] + self.shapes[g][2], self.shapes[g][1]
        r, c = np.broadcast_arrays(np.asarray(r), np.asarray(c))
        source = np.broadcast_to(np.asarray(source_base), r.shape)
        lower = r >= c
        r, c, source = r[lower], c[lower], source[lower]
        base = ((b * s + r) * d) * bp + c
        t = np.arange(d)
        stride = np.broadcast_to(np.asarray(source_stride), lower.shape)[lower]
        dst[g].append((base[..., None] + t * bp).ravel())
        src[g].append((source[..., None] + t * stride[..., None]).ravel())
        sign[g].append(np.full(dst[g][-1].shape, value))


def _add_blocks_of_h(assembly, pattern, symbolic):
    """$H$'s diagonal blocks and the identity on padded pivots, then its off-diagonal blocks and
    their transposes, each in the front where the earlier of its two blocks is a pivot."""
    n, d, p = pattern.num_blocks, pattern.block_size, pattern.num_pairs
    order, position, piv = symbolic.order, symbolic.position, symbolic.pivots
    add, slots, where, shapes = assembly.add, assembly.slots, assembly.where, assembly.shapes
    for k in range(len(piv)):
        s_piv = np.arange(len(piv[k]))
        add(k, s_piv, s_piv, order[piv[k]] * d, 1)
        s_pad = np.arange(len(piv[k]), shapes[where[k, 0]][1])
        add(k, s_pad, s_pad, (n + 2 * p) * d, 1)
    pa, pb = position[pattern.rows], position[pattern.cols]
    owner = assembly.front_of[np.minimum(pa, pb)]
    for k in np.unique(owner):
        q = np.flatnonzero(owner == k)
        sa, sb = slots(k, pa[q]), slots(k, pb[q])
        add(k, sa, sb, (n + q) * d, 1)  # H[r, c]
        add(k, sb, sa, (n + p + q) * d, 1)  # H[c, r] = H[r, c]^T


def _add_update_products(assembly, symbolic):
    """The fronts' update products $L_{21} L_{21}^\top$, each block subtracted in the front where
    its column is a pivot (a descendant's update is never copied through the fronts between)."""
    d, upd, num_fronts = assembly.d, symbolic.updates, len(symbolic.pivots)
    where, shapes, offsets = assembly.where, assembly.shapes, assembly.offsets
    entries = []  # per front: (row position, column position, source row, stride)
    for c in range(num_fronts):
        u = upd[c]
        if len(u):
            gc, bc = where[c]
            cu = shapes[gc][2]
            t1, t2 = np.tril_indices(len(u))
            source = offsets[gc] + (bc * cu + t1) * d * cu + t2
            entries.append((u[t1], u[t2], source, np.full(len(t1), cu)))
    if entries:
        row_pos, col_pos, source, stride = map(np.concatenate, zip(*entries))
        target = assembly.front_of[col_pos]
        by_target = np.argsort(target, kind="stable")
        bounds = np.searchsorted(target[by_target], np.arange(num_fronts + 1))
        for k in range(num_fronts):
            q = by_target[bounds[k] : bounds[k + 1]]
            if len(q):
                rows, cols = assembly.slots(k, row_pos[q]), assembly.slots(k, col_pos[q])
                assembly.add(k, rows, cols, source[q], stride[q], -1.0)


def _batch(assembly, g, members, pattern, symbolic):
    """Batch `g` of the fronts `members`: its pivot and update blocks (padded with block n), its
    assembly matrix from the entries added, and its update blocks' scatter."""
    from scipy.sparse import csr_matrix

    n, d = pattern.num_blocks, pattern.block_size
    order, piv, upd = symbolic.order, symbolic.pivots, symbolic.updates
    bsize, bp, bu = assembly.shapes[g]
    s = bp + bu
    pivot_index = np.full((bsize, bp), n, dtype=np.int64)
    update_index = np.full((bsize, bu), n, dtype=np.int64)
    for b, k in enumerate(members):
        pivot_index[b, : len(piv[k])] = order[piv[k]]
        update_index[b, : len(upd[k])] = order[upd[k]]
    d_all, s_all = np.concatenate(assembly.dst[g]), np.concatenate(assembly.src[g])
    matrix = csr_matrix(
        (np.concatenate(assembly.sign[g]), (d_all, s_all)),
        shape=(bsize * s * d * bp, assembly.work_rows),
    )
    matrix.sum_duplicates()
    slot = np.flatnonzero(update_index.ravel() < n)
    targets, target = np.unique(update_index.ravel()[slot], return_inverse=True)
    scatter = None
    if len(targets) < len(slot):
        scatter = csr_matrix(
            (np.ones(len(slot)), (target.ravel(), slot)),
            shape=(len(targets), update_index.size),
        )
    return _Batch(pivot_index, update_index, matrix, assembly.offsets[g], targets, scatter)
