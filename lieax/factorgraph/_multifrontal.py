r"""The multifrontal block Cholesky factorization $H = L L^\top$ of the block normal equations
(`_block_pattern`), and the solve with it from inside JAX (`cholesky_solve`).

The symbolic part runs once per graph in NumPy: a fill-reducing order (`_ordering`: minimum
degree, or nested dissection where minimum degree's elimination tree is tall, such as an IMU
smoother's chain, whose batches are then mostly fixed cost), the elimination tree, supernodes and
a batch schedule (`_cholesky_analysis`). The numeric part (Duff and Reid's multifrontal method;
Liu, "The multifrontal method for sparse matrix solution", SIAM Review 1992) runs in C++ behind
an XLA custom call where the native library is built (`_native_cholesky`: front by front in
postorder, extend-add of the children's update matrices, BLAS and LAPACK on the larger fronts;
JAX's persistent cache keeps the programs that call it), else on the host with NumPy and LAPACK,
called from the jitted loop through `host_call`: per batch, one sparse ±1 product assembles the
fronts' pivot columns (original entries, less the update products of descendants;
`_front_assembly`), then LAPACK factors the pivot blocks (`_host_triangular`) and one batched
product forms the front's update product. Both read the same analysis; the native one took
0.1-0.6x the NumPy one's time per solve on the g2o sets of `benchmarks/pgo.py`
(`benchmarks/cholesky.py`), so NumPy's is the fallback only.
"""

import threading
import weakref

import jax
import numpy as np

from .. import _threads
from .._host_call import host_call
from . import _native_cholesky
from ._cholesky_analysis import _plan_stats, _Symbolic
from ._front_assembly import _numpy_batches
from ._host_triangular import _cholesky_inverse, _cholesky_solve
from ._ordering import minimum_degree_order, nested_dissection_order

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
        if native():
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
    if native():
        if not isinstance(plan, CholeskyPlan):
            plan = plan()  # the analysis, waited for here (`Layout.start_plan` began it)
        return _native_cholesky.solve(plan.native_key(), diag, off, rhs)
    plan_of = plan if callable(plan) and not isinstance(plan, CholeskyPlan) else lambda: plan
    result = jax.ShapeDtypeStruct(rhs.shape, rhs.dtype)
    _threads.prepare()  # (the thread pools listed here, not in the callback)
    return host_call(lambda *system: _host_solve(plan_of(), *system), result, diag, off, rhs)


def native() -> bool:
    """Whether `cholesky_solve` runs the native library's custom call (built, and JAX on the
    CPU), not the host callback of its NumPy path."""
    return _native_cholesky.available() and jax.default_backend() == "cpu"


# plans named by key for `cholesky_solve_keyed`'s host path (the native path's registry is the
# library's); an entry lives as long as its plan
_KEYED = weakref.WeakValueDictionary()


def keep_keyed(plan):
    """`plan.native_key()` where the native library serves `cholesky_solve_keyed` (`native()`),
    else `plan.key` with the plan kept for its host path; the key stays valid while `plan`
    lives."""
    if native():
        return plan.native_key()
    _KEYED[plan.key] = plan
    return plan.key


def cholesky_solve_keyed(key, diag, off, rhs):
    """`cholesky_solve` by a plan named at run time: `key` the operand
    `_native_cholesky.key_words(keep_keyed(plan))`; `off` may hold more pair blocks than the
    plan's pattern (its first `num_pairs` are the plan's). One compiled program serves every
    plan of the shapes of `diag`, `off` and `rhs` (`_buckets`). The native custom call on the
    CPU, else the host callback of `plan.solve`."""
    if native():
        return _native_cholesky.solve_keyed(key, diag, off, rhs)

    def solve(words, diag, off, rhs):
        plan = _KEYED[int(words[0]) | (int(words[1]) << 32)]
        return _host_solve(plan, diag, off[: plan.pattern.num_pairs], rhs)

    _threads.prepare()
    return host_call(solve, jax.ShapeDtypeStruct(rhs.shape, rhs.dtype), key, diag, off, rhs)


def _host_solve(plan, diag, off, rhs):
    """`plan.solve` with the BLAS pools on one thread below `lieax._threads.PARALLEL_FLOPS`
    multiply-adds per factorization (every pose graph: sphere2500's 2.4e8 ran 10-19x faster on
    one thread than on two on a busy 2-core machine), else on lieax's thread setting; the
    previous counts restored after it (`lieax._threads`)."""
    threads = _threads.threads_for(plan.stats["flops"], _threads.PARALLEL_FLOPS)
    with _threads.blas_limited(threads):
        return plan.solve(diag, off, rhs)


__all__ = ["CholeskyPlan", "cholesky_solve", "cholesky_solve_keyed", "keep_keyed"]
