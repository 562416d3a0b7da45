r"""Block-sparse normal equations, and their solvers (for `lieax.factorgraph`, and so for pose
graphs).

The matrix is symmetric with `n` diagonal blocks of size `d` (one per pose or variable) and one
off-diagonal block per pair joined by a factor: `diag` `(n, d, d)` holds $H_{aa}$, `off` `(p, d, d)`
holds $H_{ab}$ for the pairs `rows[k] = a < b = cols[k]` of a fixed `BlockPattern`
($H_{ba} = H_{ab}^\top$). Assembly is a segment sum over edges into these fixed slots, so
nothing is rebuilt from one iteration to the next.

Three solvers work on these blocks:

- `CholeskyPlan`: a multifrontal block Cholesky factorization $H = L L^\top$. The symbolic part
  runs once per graph in numpy: a minimum-degree ordering of the block graph (SuperLU's multiple
  minimum degree on $A^\top + A$, through `scipy.sparse.linalg.splu`; SciPy is already a dependency
  of JAX), or nested dissection (`nested_dissection_order`) where minimum degree's elimination
  tree is tall (a chain, such as an IMU smoother, whose batches are then mostly fixed cost), the
  elimination tree, supernodes with relaxed amalgamation, and a schedule that groups fronts of
  the same height in the tree and similar size into batches. The numeric part (Duff and
  Reid's multifrontal method; Liu, "The multifrontal method for sparse matrix solution", SIAM
  Review 1992) runs in C++ behind an XLA custom call where the native library is built
  (`_native_cholesky`: front by front in postorder, extend-add of the children's update
  matrices, BLAS and LAPACK on the larger fronts; JAX's persistent cache keeps the programs
  that call it), else on the host with numpy and LAPACK, called from the jitted loop through
  `host_call`: per batch, one sparse ±1 product assembles the fronts' pivot columns (original
  entries, less the update products of descendants), then LAPACK factors the pivot blocks and
  one batched product forms the front's update product. Both read the same analysis; the
  native one took 0.1-0.6x the NumPy one's time per solve on the g2o sets of
  `benchmarks/pgo.py` (`benchmarks/cholesky.py`), so NumPy's is the fallback only.
- `dense_solve`: the dense matrix and its Cholesky factor, inside JAX, for graphs of a few
  hundred unknowns (`lieax.graph.optimize` picks it below a measured crossover).
- `pcg`: conjugate gradients preconditioned by the inverse diagonal blocks (block Jacobi), with
  matrix-vector products by segment sums; no factorization, for large graphs on GPUs.
"""

import dataclasses
import threading

import jax
import jax.numpy as jnp
import numpy as np
from jax import lax

from .. import _threads
from .._host_call import host_call
from . import _native_cholesky

# ---- the pattern and assembly -------------------------------------------------------------------


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


# ---- symbolic analysis (numpy, once per graph) ---------------------------------------------------


def minimum_degree_order(num_blocks, rows, cols):
    r"""A fill-reducing elimination order (new position -> block) of the graph with edges
    `(rows, cols)`: SuperLU's multiple minimum degree on $A^\top + A$ (`splu` is asked to factor a
    diagonally dominant matrix with this pattern and its column permutation is read back)."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.linalg import splu

    n = num_blocks
    if n == 1:
        return np.zeros(1, dtype=np.int64)
    degree = np.bincount(np.concatenate([rows, cols]), minlength=n).astype(np.float64)
    ones = -np.ones(len(rows))
    matrix = coo_matrix(
        (
            np.concatenate([ones, ones, degree + 1.0]),
            (
                np.concatenate([rows, cols, np.arange(n)]),
                np.concatenate([cols, rows, np.arange(n)]),
            ),
        ),
        shape=(n, n),
    ).tocsc()
    lu = splu(
        matrix, permc_spec="MMD_AT_PLUS_A", diag_pivot_thresh=0.0, options={"SymmetricMode": True}
    )
    return np.argsort(lu.perm_c).astype(np.int64)


def nested_dissection_order(num_blocks, rows, cols, *, leaf=128):
    r"""A fill-reducing elimination order (new position -> block) by nested dissection on level
    structures (George, "Nested dissection of a regular finite element mesh", SIAM J. Numer.
    Anal. 1973; George and Liu, "Computer Solution of Large Sparse Positive Definite Systems",
    1981, Ch. 8): from a pseudo-peripheral block, the breadth-first level that halves the blocks
    separates the rest into the nearer and the farther part (only its blocks adjacent to the
    farther part are kept in the separator); both parts are ordered recursively, then the
    separator. Parts of at most `leaf` blocks are ordered by `minimum_degree_order`. Its
    elimination tree is shallow (about $\log_2$ of the blocks on a chain such as an IMU
    smoother, where minimum degree gives a path), so the numeric phase runs far fewer batches."""
    from scipy.sparse import coo_matrix
    from scipy.sparse.csgraph import connected_components, shortest_path

    n = num_blocks
    adjacency = coo_matrix(
        (np.ones(2 * len(rows)), (np.concatenate([rows, cols]), np.concatenate([cols, rows]))),
        shape=(n, n),
    ).tocsr()
    result = []

    def by_minimum_degree(nodes, graph):
        upper = graph.tocoo()
        keep = upper.row < upper.col
        return nodes[minimum_degree_order(len(nodes), upper.row[keep], upper.col[keep])]

    def levels(graph, start):
        """Breadth-first distances from `start` (a connected graph)."""
        distance = shortest_path(graph, method="D", unweighted=True, indices=start)
        return distance.astype(np.int64)

    def dissect(nodes, graph):
        if len(nodes) <= leaf:
            result.append(by_minimum_degree(nodes, graph))
            return
        count, label = connected_components(graph, directed=False)
        if count > 1:
            for c in range(count):
                part = np.flatnonzero(label == c)
                dissect(nodes[part], graph[part][:, part])
            return
        # from a block farthest from block 0: a pseudo-peripheral block, nearly
        distance = levels(graph, int(np.argmax(levels(graph, 0))))
        height = int(distance.max())
        if height < 2:
            result.append(by_minimum_degree(nodes, graph))
            return
        middle = int(np.searchsorted(np.cumsum(np.bincount(distance)), len(nodes) / 2))
        middle = min(max(middle, 1), height - 1)
        farther = distance > middle
        separator = (distance == middle) & (graph @ farther.astype(np.float64) > 0)
        nearer = ~farther & ~separator
        for part in (nearer, farther):
            index = np.flatnonzero(part)
            dissect(nodes[index], graph[index][:, index])
        result.append(nodes[separator])

    dissect(np.arange(n), adjacency)
    return np.concatenate(result).astype(np.int64)


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


# work arrays a plan keeps, one per thread that factors with it (`CholeskyPlan._work`)
_MAX_BUFFERS = 4

# nested dissection is tried when the batches' fixed cost is this share of the modelled time
# of minimum degree's plan or more (a tall elimination tree, as a chain's: an IMU smoother)
_DISSECTION_SHARE = 0.6


class CholeskyPlan:
    """The symbolic block Cholesky factorization of a `BlockPattern` (see the module docstring).

    Build it once with `CholeskyPlan.analyze(pattern)`; `plan.factor(diag, off)` then factors
    numerically (numpy and LAPACK on the host) and `plan.solve(diag, off, rhs)` factors and
    solves; `cholesky_solve` calls it from inside `jit`. Each thread keeps its own work
    array, so threads may share a plan.

    The numeric phase keeps every entry of the assembly in one work array of rows of `d` scalars
    (a `d × d` block is `d` such rows): the rows of $H$'s diagonal blocks, of its off-diagonal
    blocks and of their transposes, a `d × d` identity (added to the padded pivot blocks by the
    assembly), then the update product $L_{21} L_{21}^\top$ of every front, each stored as a
    plain `(U d, U d)` matrix. A batch's fronts are one sparse ±1 matrix times that array,
    reshaped to `(B, S d, P d)` without any transpose: only their pivot columns, and of those
    only the lower block triangle (positions in a front follow the elimination order, and
    nothing reads the upper blocks). A front's Schur complement $F_{22} - L_{21} L_{21}^\top$
    is never formed: $F_{22}$ holds nothing but its children's Schur complements (an entry of
    $H$ is assembled in the front where its earlier block is a pivot), so each block of an
    update product is subtracted once, in the front where its column becomes a pivot, instead
    of being extended and subtracted from front to front up to there (measured with the other
    changes of that session, the host solve: 0.85x the time on smallGrid3D, 0.75-0.9x on
    sphere2500 and M3500, interleaved in one process). Every batch but the roots gets the
    inverses of its pivot blocks' Cholesky factors (`_cholesky_inverse`), so that its triangular
    solves, here and in the substitutions, are batched products; the roots keep their factors
    for `_cholesky_solve`. The update products are written in place into the work array, which
    is kept between factorizations.

    With the native library the numeric phase is `_native_cholesky`'s (registered by
    `analyze` under the plan's `key`), and the NumPy path's batches and assembly matrices, most
    of the analysis' time, are built only when `factor` or `solve` first needs them
    (`lieax.factorgraph.marginal_covariances`, tests).

    **Attributes:** `order` (the elimination order of the blocks), `key` (the native registry's
    key of the pattern and the analysis options), `stats` (the ordering, fronts,
    batches, tree height, multiply-adds of one factorization with and without padding, stored
    blocks of $L$).
    """

    def __init__(self, pattern, symbolic, ordering):
        self.pattern = pattern
        self.order = symbolic.order
        self.stats = _plan_stats(pattern, symbolic, ordering)
        self._symbolic = symbolic
        self._numpy = None  # `(batches, work_rows)`, built on first use (`_numpy_structures`)
        self._numpy_lock = threading.Lock()
        self._buffers = {}  # thread id -> work array (see `_work`)
        self._buffers_lock = threading.Lock()
        self._registered = False

    def native_key(self):
        """`key`, with this plan registered in the native library's registry (once; `analyze`
        registers where the library is available, so this registers only a plan analysed
        without it)."""
        with self._numpy_lock:
            if not self._registered:
                single = _threads.threads_for(self.stats["flops"], _threads.PARALLEL_FLOPS) == 1
                _native_cholesky.register(self, self.key, self._symbolic, single)
                self._registered = True
        return self.key

    def _numpy_structures(self):
        """The NumPy path's batches and work array size (`_numpy_batches`), built on first use:
        most of the analysis' time, which the native path does not need."""
        with self._numpy_lock:
            if self._numpy is None:
                self._numpy = _numpy_batches(self.pattern, self._symbolic)
        return self._numpy

    @property
    def batches(self):
        """The NumPy path's batches of fronts (`_Batch`)."""
        return self._numpy_structures()[0]

    @property
    def work_rows(self):
        """The rows of the NumPy path's work array."""
        return self._numpy_structures()[1]

    def _work(self, dtype):
        """The work array, kept between factorizations (one per thread): a fresh one would cost
        a page fault per 4 KiB at every factorization. Kept by thread id, not in a
        `threading.local`: XLA runs the host callback on its own (non-Python) threads, whose
        Python thread state, and with it a `threading.local`'s data, is created and dropped at
        every call (measured: 85 work arrays allocated in 210 solves on 2 threads; sphere2500's
        is 45 MB, 11k page faults per solve). At most `_MAX_BUFFERS` are kept (the oldest
        thread's goes first)."""
        thread = threading.get_ident()
        work = self._buffers.get(thread)
        if work is None or work.dtype != dtype:
            work = np.empty((self.work_rows, self.pattern.block_size), dtype=dtype)
            with self._buffers_lock:  # a thread evicted here keeps its array while it runs
                self._buffers.pop(thread, None)
                while len(self._buffers) >= _MAX_BUFFERS:
                    self._buffers.pop(next(iter(self._buffers)))
                self._buffers[thread] = work
        return work

    def __repr__(self):
        return f"CholeskyPlan({self.stats})"

    @classmethod
    def analyze(cls, pattern, *, order=None, max_pivots=(2, 8, 32), zero_fraction=(0.5, 0.1)):
        """The plan for `pattern`: `order` (elimination order of the blocks; default
        `minimum_degree_order`, or `nested_dissection_order` where minimum degree's tree is tall
        and nested dissection's plan is faster by the cost model `_batch_seconds`),
        amalgamation limits `max_pivots` (blocks) and `zero_fraction` (see `_amalgamate`)."""
        n, rows, cols = pattern.num_blocks, pattern.rows, pattern.cols
        given = None if order is None else np.asarray(order).tolist()
        ordering = "given"
        if order is None:
            ordering = "minimum degree"
            order = minimum_degree_order(n, rows, cols)
            symbolic = _Symbolic.of_order(pattern, order, max_pivots, zero_fraction)
            if symbolic.batch_share >= _DISSECTION_SHARE:
                dissected = _Symbolic.of_order(
                    pattern, nested_dissection_order(n, rows, cols), max_pivots, zero_fraction
                )
                if dissected.seconds < symbolic.seconds:
                    ordering, symbolic = "nested dissection", dissected
        else:
            order = np.asarray(order, dtype=np.int64)
            if order.shape != (n,) or np.any(np.sort(order) != np.arange(n)):
                raise ValueError("order must be a permutation of the blocks.")
            symbolic = _Symbolic.of_order(pattern, order, max_pivots, zero_fraction)
        plan = cls(pattern, symbolic, ordering)
        plan.key = _native_cholesky.analysis_key(pattern, (given, max_pivots, zero_fraction))
        if _native_cholesky.available():
            plan.native_key()
        else:  # the NumPy path's structures, here where the analysis overlaps the compilation
            plan._numpy_structures()
        return plan

    # ---- numeric phase (numpy) -------------------------------------------------------------------
    def factor(self, diag, off):
        """The numeric factorization of $H$ from `diag` `(n, d, d)` and `off` `(p, d, d)`
        (numpy arrays), per batch `(M, L21)`: `L21` `(B, U d, P d)`, and `M` `(B, P d, P d)` the
        inverses $L_{11}^{-1}$ of the pivot blocks' Cholesky factors, so that both substitutions
        are batched products; for a batch of roots (no update rows, `L21` None) `M` is $L_{11}$
        itself, as one `potrs` there costs a fraction of the inverse (the root front is the
        largest: 180 × 180 on smallGrid3D).
        Raises `numpy.linalg.LinAlgError` when $H$ is not positive definite."""
        n, d, p = self.pattern.num_blocks, self.pattern.block_size, self.pattern.num_pairs
        diag, off = np.asarray(diag), np.asarray(off)
        work = self._work(diag.dtype)
        work[: n * d] = diag.reshape(n * d, d)
        work[n * d : (n + p) * d] = off.reshape(p * d, d)
        work[(n + p) * d : (n + 2 * p) * d] = off.transpose(0, 2, 1).reshape(p * d, d)
        work[(n + 2 * p) * d : (n + 2 * p + 1) * d] = np.eye(d)
        factors = []
        for batch in self.batches:
            B, P, U = batch.shape
            pd, ud = P * d, U * d
            front = (batch.assembly @ work).reshape(B, pd + ud, pd)
            f11 = front[:, :pd]
            if U == 0:
                factors.append((np.linalg.cholesky(f11), None))
                continue
            l11_inv = _cholesky_inverse(f11)
            l21 = front[:, pd:] @ l11_inv.transpose(0, 2, 1)
            # the update product, written in place into the work array for the ancestors
            update = work[batch.work_offset : batch.work_offset + B * ud * U].reshape(B, ud, ud)
            np.matmul(l21, l21.transpose(0, 2, 1), out=update)
            factors.append((l11_inv, l21))
        return factors

    def solve_factored(self, factors, rhs):
        """$H^{-1}$ `rhs` for `rhs` `(n, d)` (numpy), by forward and back substitution. A batch
        whose fronts share no update block subtracts its updates by one indexed assignment
        (row n, the padding's, takes whichever update comes last; it reaches only padded pivots,
        whose columns of `L21` are zero), another sums them per block first (a sparse 0/1
        product): `numpy.subtract.at`, which accumulates repeated rows, cost 11 µs a batch on
        smallGrid3D where either costs 3-5 µs, a third of the whole substitution. A batch of
        roots does both substitutions at once in the forward pass (`_cholesky_solve`)."""
        n, d = self.pattern.num_blocks, self.pattern.block_size
        x = np.zeros((n + 1, d), dtype=rhs.dtype)
        x[:n] = rhs
        for batch, (m, l21) in zip(self.batches, factors):
            B, P, U = batch.shape
            b = x[batch.pivot_index].reshape(B, P * d, 1)
            if l21 is None:  # roots: both substitutions at once (nothing else reads their rows)
                x[batch.pivot_index] = _cholesky_solve(m, b).reshape(B, P, d)
                continue
            y = m @ b
            x[batch.pivot_index] = y.reshape(B, P, d)
            if U:
                update = (l21 @ y).reshape(B, U, d)
                if batch.scatter is None:  # a plain indexed update (only the padding row repeats)
                    x[batch.update_index] -= update
                else:
                    x[batch.targets] -= batch.scatter @ update.reshape(B * U, d)
        for batch, (m, l21) in zip(reversed(self.batches), reversed(factors)):
            if l21 is None:
                continue
            B, P, U = batch.shape
            y = x[batch.pivot_index].reshape(B, P * d, 1)
            y -= l21.transpose(0, 2, 1) @ x[batch.update_index].reshape(B, U * d, 1)
            x[batch.pivot_index] = (m.transpose(0, 2, 1) @ y).reshape(B, P, d)
        x[n] = 0.0
        return x[:n]

    def solve(self, diag, off, rhs):
        """$H^{-1}$ `rhs` (numpy in and out); NaN when $H$ is not positive definite."""
        try:
            factors = self.factor(diag, off)
        except np.linalg.LinAlgError:
            return np.full(np.shape(rhs), np.nan, dtype=np.asarray(rhs).dtype)
        return self.solve_factored(factors, np.asarray(rhs))


def _numpy_batches(pattern, symbolic):
    """`(batches, work_rows)`: the NumPy path's batches of the fronts of `symbolic`, with their
    assembly matrices, and the rows of its work array (see `CholeskyPlan`)."""
    from scipy.sparse import csr_matrix

    n, d, p = pattern.num_blocks, pattern.block_size, pattern.num_pairs
    rows, cols = pattern.rows, pattern.cols
    order, position = symbolic.order, symbolic.position
    piv, upd = symbolic.pivots, symbolic.updates
    members_of = symbolic.batches
    num_fronts = len(piv)

    where = np.empty((num_fronts, 2), dtype=np.int64)  # front -> (batch, position)
    shapes = []
    work_rows = (n + 2 * p + 1) * d  # H's blocks, the identity (padding), update products
    offsets = []
    for g, members in enumerate(members_of):
        where[members, 0] = g
        where[members, 1] = np.arange(len(members))
        bp = max(len(piv[k]) for k in members)
        bu = max(len(upd[k]) for k in members)
        shapes.append((len(members), bp, bu))
        offsets.append(work_rows)
        work_rows += len(members) * bu * d * bu
    front_of = np.empty(n, dtype=np.int64)  # elimination position -> front
    for k, a in enumerate(piv):
        front_of[a] = k

    def slots(k, positions):
        """Rows of elimination positions in front k's layout [pivots (padded) | updates]."""
        bp = shapes[where[k, 0]][1]
        in_pivots = np.searchsorted(piv[k], positions)
        in_pivots_clipped = np.minimum(in_pivots, len(piv[k]) - 1)
        is_pivot = piv[k][in_pivots_clipped] == positions
        return np.where(is_pivot, in_pivots, bp + np.searchsorted(upd[k], positions))

    # every block is d segments (rows of d scalars) of the work array, at base + r * stride
    dst = [[] for _ in members_of]
    src = [[] for _ in members_of]
    sign = [[] for _ in members_of]

    def add(k, r, c, source_base, source_stride, value=1.0):
        """Blocks (r, c) of front k from the work array, times `value`; only the lower block
        triangle (r >= c) of the pivot columns (c < pivots) is assembled: the factorization
        reads no other block."""
        g, b = where[k]
        s, bp = shapes[g][1] + shapes[g][2], shapes[g][1]
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

    # diagonal blocks of H, and the identity on padded pivots
    for k in range(num_fronts):
        s_piv = np.arange(len(piv[k]))
        add(k, s_piv, s_piv, order[piv[k]] * d, 1)
        s_pad = np.arange(len(piv[k]), shapes[where[k, 0]][1])
        add(k, s_pad, s_pad, (n + 2 * p) * d, 1)
    # off-diagonal blocks: in the front where the earlier of the two is a pivot
    pa, pb = position[rows], position[cols]
    owner = front_of[np.minimum(pa, pb)]
    for k in np.unique(owner):
        q = np.flatnonzero(owner == k)
        sa, sb = slots(k, pa[q]), slots(k, pb[q])
        add(k, sa, sb, (n + q) * d, 1)  # H[r, c]
        add(k, sb, sa, (n + p + q) * d, 1)  # H[c, r] = H[r, c]^T
    # the fronts' update products L21 L21^T, each block subtracted in the front where its
    # column is a pivot (a descendant's update is never copied through the fronts between)
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
        target = front_of[col_pos]
        by_target = np.argsort(target, kind="stable")
        bounds = np.searchsorted(target[by_target], np.arange(num_fronts + 1))
        for k in range(num_fronts):
            q = by_target[bounds[k] : bounds[k + 1]]
            if len(q):
                add(k, slots(k, row_pos[q]), slots(k, col_pos[q]), source[q], stride[q], -1.0)

    batches = []
    for g, members in enumerate(members_of):
        bsize, bp, bu = shapes[g]
        s = bp + bu
        pivot_index = np.full((bsize, bp), n, dtype=np.int64)
        update_index = np.full((bsize, bu), n, dtype=np.int64)
        for b, k in enumerate(members):
            pivot_index[b, : len(piv[k])] = order[piv[k]]
            update_index[b, : len(upd[k])] = order[upd[k]]
        d_all, s_all = np.concatenate(dst[g]), np.concatenate(src[g])
        assembly = csr_matrix(
            (np.concatenate(sign[g]), (d_all, s_all)), shape=(bsize * s * d * bp, work_rows)
        )
        assembly.sum_duplicates()
        slot = np.flatnonzero(update_index.ravel() < n)
        targets, target = np.unique(update_index.ravel()[slot], return_inverse=True)
        scatter = None
        if len(targets) < len(slot):
            scatter = csr_matrix(
                (np.ones(len(slot)), (target.ravel(), slot)),
                shape=(len(targets), update_index.size),
            )
        batches.append(
            _Batch(
                pivot_index,
                update_index,
                assembly,
                offsets[g],
                targets,
                scatter,
            )
        )
    return batches, work_rows


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


def cholesky_solve(plan, diag, off, rhs, *, pattern=None):
    """`plan.solve` from inside JAX (`jit`, `lax.while_loop`, `vmap`); NaN when $H$ is not
    positive definite. `plan` is a `CholeskyPlan`, or a function returning the default analysis
    of `pattern` (`CholeskyPlan.analyze(pattern)`; a `Layout.plan`). The native path calls it
    when the solve is traced (the custom call names the plan's key, and the plan must be
    registered when the program runs; `Layout.start_plan` begins the analysis before the loop is
    traced); the host callback calls it when the solve runs, so that its analysis overlaps the
    loop's compilation.

    With the native library (`lieax._native.available()`) and JAX on the CPU, the numeric phase
    is the C++ custom call of `_native_cholesky`, named by the plan's key, which JAX's
    persistent compilation cache can keep; otherwise `plan.solve` in a host callback
    (`host_call`; on an accelerator the blocks travel to the host and back), which it cannot
    (the custom call is registered for the CPU only)."""
    if not callable(plan) and not isinstance(plan, CholeskyPlan):
        raise TypeError(f"plan must be a CholeskyPlan or a function returning one, got {plan!r}.")
    if isinstance(plan, CholeskyPlan):
        pattern = plan.pattern
    elif pattern is None:
        raise ValueError("cholesky_solve needs the pattern of a plan given as a function.")
    expected = (pattern.num_blocks, pattern.block_size)
    if rhs.shape[-2:] != expected or diag.shape[-3:] != (*expected, pattern.block_size):
        raise ValueError(
            f"cholesky_solve: diag {diag.shape} and rhs {rhs.shape} do not match the pattern's "
            f"{pattern.num_blocks} blocks of size {pattern.block_size}."
        )
    if _native_cholesky.available() and jax.default_backend() == "cpu":
        if not isinstance(plan, CholeskyPlan):
            plan = plan()  # the analysis, waited for here (`Layout.start_plan` began it)
        return _native_cholesky.solve(plan.native_key(), diag, off, rhs)
    plan_of = plan if callable(plan) and not isinstance(plan, CholeskyPlan) else lambda: plan
    result = jax.ShapeDtypeStruct(rhs.shape, rhs.dtype)
    _threads.prepare()  # (the thread pools listed here, not in the callback)
    return host_call(lambda *system: _host_solve(plan_of(), *system), result, diag, off, rhs)


def _host_solve(plan, diag, off, rhs):
    """`plan.solve` with the BLAS pools on one thread below `lieax._threads.PARALLEL_FLOPS`
    multiply-adds per factorization (every pose graph: sphere2500's 2.4e8 ran 10-19x faster on
    one thread than on two on a busy 2-core machine), else on lieax's thread setting; the
    previous counts restored after it (`lieax._threads`)."""
    threads = _threads.threads_for(plan.stats["flops"], _threads.PARALLEL_FLOPS)
    with _threads.blas_limited(threads):
        return plan.solve(diag, off, rhs)


# Host linear algebra must not wake two OpenBLAS thread pools: SciPy's wheels bundle a second
# OpenBLAS beside NumPy's, and two pools busy-waiting in one process are the slowest configuration
# on a small machine (sphere2500 took 7.8x as long with both pools at two threads as with either
# at one, 2 cores). So every operation that OpenBLAS may run on several threads (products of
# 64³ multiply-adds and more, factorizations of order 64 and more) is NumPy's, and SciPy's LAPACK
# is called only on triangles of order below 64, which OpenBLAS always inverts on the calling
# thread (`trtri` falls back to its unblocked `trti2` there; measured: process CPU time equals
# wall time up to order 64, twice it from 96 with two threads allowed). NumPy has no triangular
# inverse, and `numpy.linalg.inv` (LU) is 2.5-3.5x slower than `trtri` from order 12 up, so
# larger triangles are a blocked recursion on NumPy products (Higham, "Accuracy and Stability of
# Numerical Algorithms", Sec. 14.2) down to blocks below 64, and the tiniest (order ≤ 8, where
# the per-call cost dominates) are one batched `numpy.linalg.inv`.
_SINGLE_THREAD_LIMIT = 64
_BATCHED_LIMIT = 8


def _lower_inverse(lower):
    r"""$L^{-1}$ for a batch `(B, n, n)` of lower-triangular $L$:
    $[A, 0; C, D]^{-1} = [A^{-1}, 0; -D^{-1} C A^{-1}, D^{-1}]$ for $n \ge 64$, LAPACK's
    `trtri` one matrix at a time below, one batched `numpy.linalg.inv` up to order 8."""
    n = lower.shape[-1]
    if n <= _BATCHED_LIMIT:
        return np.linalg.inv(lower)
    if n < _SINGLE_THREAD_LIMIT:
        return _trtri_each(lower)
    h = n // 2
    a_inv = _lower_inverse(lower[:, :h, :h])
    d_inv = _lower_inverse(lower[:, h:, h:])
    result = np.zeros_like(lower)
    result[:, :h, :h] = a_inv
    result[:, h:, h:] = d_inv
    result[:, h:, :h] = -(d_inv @ (lower[:, h:, :h] @ a_inv))
    return result


def _cholesky_inverse(matrix):
    r"""$L^{-1}$ for the Cholesky factors $L L^\top$ of a batch `(B, n, n)` of symmetric positive
    definite matrices (only their lower triangles are read): for orders 9 to 63, LAPACK's `potrf`
    and `trtri` one matrix at a time on the same Fortran-ordered copy (below order 64 OpenBLAS
    runs both on the calling thread, see `_SINGLE_THREAD_LIMIT`), which skips the batched
    `numpy.linalg.cholesky`'s layout copies and calls; `_lower_inverse` of
    `numpy.linalg.cholesky` otherwise."""
    n = matrix.shape[-1]
    if n <= _BATCHED_LIMIT or n >= _SINGLE_THREAD_LIMIT:
        return _lower_inverse(np.linalg.cholesky(matrix))
    from scipy.linalg import lapack

    potrf, trtri = lapack.get_lapack_funcs(("potrf", "trtri"), (matrix,))
    result = np.empty_like(matrix)
    for b in range(matrix.shape[0]):
        # the C-ordered lower triangle is the Fortran-ordered upper triangle of the transpose
        upper, info = potrf(matrix[b].T, lower=0, clean=1)
        if info != 0:
            raise np.linalg.LinAlgError("matrix is not positive definite")
        inverse, info = trtri(upper, lower=0, overwrite_c=1)
        if info != 0:
            raise np.linalg.LinAlgError("singular triangular factor")
        result[b] = inverse.T
    return result


def _cholesky_solve(lower, rhs):
    r"""$(L L^\top)^{-1}$ `rhs` for a batch `(B, n, n)` of lower-triangular $L$ and `rhs`
    `(B, n, 1)`: LAPACK's `potrs` one matrix at a time (in place on the transpose, as
    `_trtri_each`). With one right-hand side OpenBLAS's triangular solves stay on the calling
    thread at every order (measured with two threads allowed: process CPU time equals wall time
    up to order 400), and one call does both substitutions of a root front: 12 µs where
    `_lower_solve`'s two recursions took 50 µs (order 180, smallGrid3D's root)."""
    from scipy.linalg import lapack

    (potrs,) = lapack.get_lapack_funcs(("potrs",), (lower,))
    result = np.empty_like(rhs)
    for b in range(lower.shape[0]):
        result[b], info = potrs(lower[b].T, rhs[b], lower=0)
        if info != 0:
            raise np.linalg.LinAlgError("singular triangular factor")
    return result


def _trtri_each(lower):
    """`trtri` on each matrix of the batch. A C-ordered lower triangle is the Fortran-ordered
    upper triangle of its transpose, so LAPACK reads it in place and the transpose of its result
    is the inverse."""
    from scipy.linalg import lapack

    (trtri,) = lapack.get_lapack_funcs(("trtri",), (lower,))
    result = np.empty_like(lower)
    for b in range(lower.shape[0]):
        inverse, info = trtri(lower[b].T, lower=0)
        if info != 0:
            raise np.linalg.LinAlgError("singular triangular factor")
        result[b] = inverse.T
    return result


def _lower_solve(lower, rhs, *, transpose=False):
    r"""$L^{-1}$ `rhs` (or $L^{-\top}$ `rhs`) for a batch `(B, n, n)` of lower-triangular $L$
    and `rhs` `(B, n, k)`: by blocks for $n \ge 64$, with $L = [A, 0; C, D]$,
    $L^{-1} [b_1; b_2] = [A^{-1} b_1;\ D^{-1}(b_2 - C A^{-1} b_1)]$ and
    $L^{-\top} [b_1; b_2] = [A^{-\top}(b_1 - C^\top D^{-\top} b_2);\ D^{-\top} b_2]$; LAPACK's
    `trtrs` one matrix at a time below (as `_trtri_each`, in place on the transpose)."""
    n = lower.shape[-1]
    if n < _SINGLE_THREAD_LIMIT:
        from scipy.linalg import lapack

        (trtrs,) = lapack.get_lapack_funcs(("trtrs",), (lower,))
        result = np.empty_like(rhs)
        for b in range(lower.shape[0]):
            # L y = r is Uᵀ y = r for the upper triangle U = Lᵀ that LAPACK sees
            result[b], info = trtrs(lower[b].T, rhs[b], lower=0, trans=0 if transpose else 1)
            if info != 0:
                raise np.linalg.LinAlgError("singular triangular factor")
        return result
    h = n // 2
    a, c, d = lower[:, :h, :h], lower[:, h:, :h], lower[:, h:, h:]
    if transpose:
        y2 = _lower_solve(d, rhs[:, h:], transpose=True)
        y1 = _lower_solve(a, rhs[:, :h] - np.swapaxes(c, 1, 2) @ y2, transpose=True)
    else:
        y1 = _lower_solve(a, rhs[:, :h])
        y2 = _lower_solve(d, rhs[:, h:] - c @ y1)
    return np.concatenate([y1, y2], axis=1)


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


# ---- conjugate gradients -------------------------------------------------------------------------


def pcg(pattern, diag, off, rhs, *, tolerance=1e-10, max_iterations=None):
    r"""Solve $H x = b$ by conjugate gradients preconditioned with the inverse diagonal blocks.

    Stops when $\|r\| \le$ `tolerance` $\|b\|$ or after `max_iterations` (default $10 n d$).
    **Returns:** `(x, iterations)`.
    """
    n, d = pattern.num_blocks, pattern.block_size
    max_iterations = 10 * n * d if max_iterations is None else max_iterations
    chol = jnp.linalg.cholesky(diag)

    def precondition(r):
        return jax.scipy.linalg.cho_solve((chol, True), r[..., None])[..., 0]

    def matvec(x):
        return block_matvec(pattern, diag, off, x)

    x = jnp.zeros_like(rhs)
    r = rhs
    z = precondition(r)
    rz = jnp.vdot(r, z)
    threshold = (tolerance * jnp.linalg.norm(rhs)) ** 2

    def cond(state):
        _, r, _, _, _, k = state
        return (jnp.vdot(r, r) > threshold) & (k < max_iterations)

    def body(state):
        x, r, z, p, rz, k = state
        q = matvec(p)
        alpha = rz / jnp.vdot(p, q)
        x = x + alpha * p
        r = r - alpha * q
        z = precondition(r)
        rz_new = jnp.vdot(r, z)
        p = z + (rz_new / rz) * p
        return x, r, z, p, rz_new, k + 1

    x, _, _, _, _, k = lax.while_loop(cond, body, (x, r, z, z, rz, jnp.zeros((), jnp.int32)))
    return x, k


def dense_solve(pattern, diag, off, rhs):
    """$H^{-1}$ `rhs` through the dense matrix and its Cholesky factor, in JAX (for graphs of a
    few poses, where the host's multifrontal factorization costs more than the dense one); NaN
    when $H$ is not positive definite. The matrix is one gather from the blocks (indices built
    in numpy at trace time)."""
    n, d = pattern.num_blocks, pattern.block_size
    values = jnp.concatenate([diag.reshape(-1), off.reshape(-1), jnp.zeros(1, diag.dtype)])
    matrix = values[_dense_index(pattern)]

    def solve(system):
        matrix, b = system
        factor = jnp.linalg.cholesky(matrix)
        return jax.scipy.linalg.cho_solve((factor, True), b)

    return solve((matrix, rhs.reshape(n * d))).reshape(n, d)


def dense_threads(pattern):
    """The BLAS threads for `dense_solve`'s factorization of `pattern` on a CPU, to be set around
    the compiled call (`lieax._threads.lapack_limited`), or `None` (no scope): XLA's CPU backend
    factors through SciPy's OpenBLAS, whose idle threads busy-wait, so one thread below
    `lieax._threads.PARALLEL_FLOPS` (order 441, Ladybug-49's cameras: 4 ms against 442 ms on two
    threads on a busy 2-core machine); below order `SINGLE_THREAD_ORDER` OpenBLAS stays on the
    calling thread anyway."""
    order = pattern.num_blocks * pattern.block_size
    if order < _threads.SINGLE_THREAD_ORDER or jax.default_backend() != "cpu":
        return None
    return _threads.threads_for(order**3 / 3, _threads.PARALLEL_FLOPS)


def _dense_index(pattern):
    """For each entry of the dense `(n d, n d)` matrix, its index in `[diag, off, 0]` (flat)."""
    n, d, p = pattern.num_blocks, pattern.block_size, pattern.num_pairs
    index = np.full((n * d, n * d), n * d * d + p * d * d, dtype=np.int32)
    r = np.arange(d)
    a = np.arange(n)[:, None, None]
    index[a * d + r[:, None], a * d + r[None, :]] = (a * d + r[:, None]) * d + r[None, :]
    k = np.arange(p)[:, None, None]
    rows, cols = pattern.rows[:, None, None], pattern.cols[:, None, None]
    source = n * d * d + (k * d + r[:, None]) * d + r[None, :]
    index[rows * d + r[:, None], cols * d + r[None, :]] = source
    index[cols * d + r[None, :], rows * d + r[:, None]] = source
    return index


def dense_matrix(pattern, diag, off):
    """The dense `(n d, n d)` matrix (tests and small problems)."""
    n, d = pattern.num_blocks, pattern.block_size
    blocks = jnp.zeros((n, n, d, d), diag.dtype)
    blocks = blocks.at[jnp.arange(n), jnp.arange(n)].set(diag)
    blocks = blocks.at[pattern.rows, pattern.cols].set(off)
    blocks = blocks.at[pattern.cols, pattern.rows].set(jnp.swapaxes(off, -1, -2))
    return blocks.transpose(0, 2, 1, 3).reshape(n * d, n * d)


__all__ = [
    "BlockPattern",
    "CholeskyPlan",
    "block_matvec",
    "cholesky_solve",
    "dense_threads",
    "dense_matrix",
    "dense_solve",
    "minimum_degree_order",
    "nested_dissection_order",
    "pcg",
]
