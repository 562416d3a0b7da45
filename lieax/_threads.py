r"""How many threads lieax's work outside XLA's own thread pool uses, and the scopes that set them.

Three kinds of lieax's work run on thread pools that XLA does not manage:
- the host multifrontal Cholesky of `lieax.factorgraph` and `lieax.graph`: its native custom
  call (SciPy's OpenBLAS for the larger fronts; the count is set per call on the calling thread
  from the setting passed through `on_change`), or without the native library NumPy's
  OpenBLAS, and SciPy's LAPACK for the small fronts, inside a host callback;
- the k-d tree's builds and queries of `lieax.icp`: the native library's helper threads (from
  `PARALLEL_NEIGHBOURS` neighbours asked for, capped by the setting passed through `on_change`;
  asleep between calls, and a call never waits for one to wake: `csrc/parallel.h`), or without
  it the host tree's (pykdtree's OpenMP), inside a host callback;
- the dense Cholesky of `lieax.factorgraph`'s `linear_solver="dense"` (bundle adjustment's reduced camera
  system), which XLA's CPU backend runs through LAPACK: jaxlib takes its LAPACK from SciPy's
  bundled OpenBLAS (`threadpoolctl.threadpool_info()` lists no other BLAS after a
  `jnp.linalg.cholesky` call, and limiting SciPy's pool alone changes its time).

OpenBLAS's worker threads busy-wait after each parallel call, and on a machine whose cores are
busy they take turns with the work itself: measured on this 2-core machine at load 15 (other jobs
running), a warm `lieax.graph.optimize` of sphere2500 took 10.6-19.3 s with both OpenBLAS pools at
their default 2 threads and 0.94-1.03 s at one (smallGrid3D: 2.7-4.5 s and 0.08-0.11 s), and a
jitted `jnp.linalg.cholesky` of order 441 took 442 ms with SciPy's pool at 2 threads and 4 ms at
one (order 1200: 3.6 s and 0.20 s). So lieax runs work below `PARALLEL_FLOPS` multiply-adds
(every pose graph of `benchmarks/pgo.py`: at most 2.4e8 per factorization) on the calling
thread, and larger work on `get_threads()` threads; pykdtree's queries go parallel from
`PARALLEL_NEIGHBOURS` neighbours asked for (below, one OpenMP thread was 6-14x faster at load 15 on
the 7-9k point clouds of `benchmarks/neighbors.py`, above the default was 1.0-1.3x faster).
Single-threaded calls wake no worker, so none is left spinning after them.

The limits are set through `threadpoolctl` around lieax's own work only and restored after it:
around the host work inside each callback (`blas_limited`, `openmp_limited`: counts of the calling
thread), and for XLA's LAPACK calls around the compiled solve that makes them
(`lapack_limited`, set by `FactorGraph.solve` and `lieax.graph.optimize` from
`lieax.factorgraph._dense_solve.dense_threads`, not inside the program, which then keeps no host
callback: JAX's persistent cache can store it, and `vmap` of its loop's `cond` works; the LAPACK
call runs on a thread XLA picks, so this limit is process-wide while it holds: another thread of
the process calling OpenBLAS meanwhile shares it; under the caller's own `jit` it is not set).

Inside a host callback the count is OpenBLAS's thread-local one (`openblas_set_num_threads_local`,
OpenBLAS 0.3.27 and later; both wheels bundle 0.3.30-0.3.31): it applies to the callback's thread
only. The process-wide `openblas_set_num_threads`, called from XLA's callback thread, did not keep
NumPy's worker asleep: smallGrid3D warm took 22 ms-2.1 s under a load of two spinning processes,
against 14-34 ms with the thread-local count, as with `OPENBLAS_NUM_THREADS=1`.

The setting: `LIEAX_NUM_THREADS` in the environment (read when lieax is imported), or
`lieax.set_threads(n)` / `with lieax.threads(n):`. `n` (a positive integer) caps the threads of
the parallel work; `None` (the default) leaves the libraries' own setting for it
(`OPENBLAS_NUM_THREADS`, `OMP_NUM_THREADS`, else one per core). Small work is single-threaded in
either case. A value that is not a positive integer, or a number of threads when no BLAS that
threadpoolctl can limit is loaded, is an error naming the setting.
"""

import contextlib
import ctypes
import os
import sys
import threading
from collections.abc import Iterator

import numpy as np

ENVIRONMENT_VARIABLE = "LIEAX_NUM_THREADS"
# Work of at least this many multiply-adds may run on several threads (see the module docstring).
PARALLEL_FLOPS = 1e10
# pykdtree queries asking for at least this many neighbours in all may run on several threads.
PARALLEL_NEIGHBOURS = 32768
# OpenBLAS factors orders below this on the calling thread anyway: no scope needed.
SINGLE_THREAD_ORDER = 64

_LOCK = threading.Lock()
_CONTROLLERS = {}  # the loaded modules it saw -> threadpoolctl.ThreadpoolController
_BLAS_SCOPE = {"depth": 0, "saved": None}


def _parse(value, setting):
    """`value` checked as a thread count (`None` for the libraries' own), errors naming `setting`."""
    if value is None:
        return None
    if isinstance(value, bool) or not isinstance(value, int | np.integer):
        raise TypeError(f"{setting} must be a positive integer or None, got {value!r}.")
    if value <= 0:
        raise ValueError(f"{setting} must be a positive integer (threads), got {value}.")
    return int(value)


def _from_environment():
    text = os.environ.get(ENVIRONMENT_VARIABLE, "").strip()
    if text in ("", "auto"):
        return None
    try:
        value = int(text)
    except ValueError:
        raise ValueError(
            f"{ENVIRONMENT_VARIABLE} must be a positive integer or 'auto', got {text!r}."
        ) from None
    return _parse(value, ENVIRONMENT_VARIABLE)


_SETTING = {"threads": _from_environment(), "source": ENVIRONMENT_VARIABLE}
# functions told the setting whenever it changes (`on_change`)
_LISTENERS = []


def on_change(listener):
    """Calls `listener(threads)` with the setting now and whenever it changes: for host work that
    reads it outside Python (the native multifrontal Cholesky's BLAS calls, made on XLA's
    threads inside a compiled program)."""
    _LISTENERS.append(listener)
    listener(_SETTING["threads"])


def _update(**setting):
    _SETTING.update(setting)
    for listener in _LISTENERS:
        listener(_SETTING["threads"])


def _controller():
    """threadpoolctl's controller of the BLAS and OpenMP libraries loaded now (rebuilt when SciPy's
    LAPACK or pykdtree has been loaded since: listing the libraries costs milliseconds)."""
    from threadpoolctl import ThreadpoolController

    key = tuple(name in sys.modules for name in ("scipy.linalg", "pykdtree.kdtree"))
    controller = _CONTROLLERS.get(key)
    if controller is None:
        controller = _CONTROLLERS.setdefault(key, ThreadpoolController())
    return controller


def _pools(user_api):
    return [lib for lib in _controller().lib_controllers if lib.user_api == user_api]


def _check_blas(setting):
    import scipy.linalg  # noqa: F401  (SciPy's OpenBLAS, jaxlib's LAPACK, loaded to be listed)

    if not _pools("blas"):
        raise RuntimeError(
            f"{setting} cannot be honoured: no BLAS whose threads threadpoolctl can set is loaded "
            "(NumPy's and SciPy's wheels bundle OpenBLAS; another BLAS may need its own variable, "
            "such as OPENBLAS_NUM_THREADS, MKL_NUM_THREADS or OMP_NUM_THREADS)."
        )


def set_threads(n: int | None) -> None:
    """Cap the threads of lieax's parallel host and LAPACK work at `n` (a positive integer), or
    leave them to the libraries' own setting (`None`, the default, or `LIEAX_NUM_THREADS`); work
    below lieax's thresholds is single-threaded either way. Process-wide for lieax's calls; see
    `lieax._threads` for what it covers and the measurements behind the thresholds.

    Raises `ValueError` / `TypeError` for a value that is not a positive integer and
    `RuntimeError` when no BLAS whose threads can be set is loaded, naming the setting."""
    setting = "lieax.set_threads(n)"
    value = _parse(n, setting)
    if value is not None:
        _check_blas(setting)
    _update(threads=value, source=setting)


def get_threads() -> int | None:
    """The cap set by `set_threads`, `threads` or `LIEAX_NUM_THREADS` (`None`: none)."""
    return _SETTING["threads"]


@contextlib.contextmanager
def threads(n: int | None) -> Iterator[None]:
    """`set_threads(n)` for the calls inside the `with` block, the previous setting restored after
    it (on every thread: lieax's host work runs on XLA's threads, not the caller's)."""
    previous = dict(_SETTING)
    setting = "lieax.threads(n)"
    value = _parse(n, setting)
    if value is not None:
        _check_blas(setting)
    _update(threads=value, source=setting)
    try:
        yield
    finally:
        _update(**previous)


def threads_for(work, parallel_from):
    """The threads for `work` (multiply-adds or neighbours): 1 below `parallel_from`, else the
    setting (`None`: the libraries' own, no limit)."""
    return 1 if work < parallel_from else get_threads()


def prepare():
    """Called at trace time by the functions that scope threads: lists the libraries (so that a
    host callback does not) and checks that an explicit setting can be honoured."""
    if get_threads() is not None:
        _check_blas(_SETTING["source"])
    else:
        _controller()


@contextlib.contextmanager
def blas_limited(threads):
    """BLAS calls made on the calling thread inside the block on `threads` threads (`None`:
    unchanged). OpenBLAS pools by `openblas_set_num_threads_local`, which sets the count of the
    calling thread only (the user's threads keep theirs), restored after the block; other BLAS
    libraries by their process-wide count (`_enter_blas`), restored when the last of the blocks
    open in the process closes.

    (Measured under a load of two spinning processes on 2 cores, smallGrid3D warm: 14-34 ms with
    the thread-local count, as with `OPENBLAS_NUM_THREADS=1`, against 22 ms-2.1 s with
    `openblas_set_num_threads` called from XLA's callback thread, which did not keep NumPy's
    worker asleep.)"""
    if threads is None:
        yield
        return
    local, shared = [], []
    for pool in _pools("blas"):
        setter = _local_setter(pool)
        (shared if setter is None else local).append(setter)
    previous = [setter(threads) for setter in local]
    if shared:
        _enter_blas(threads, only_shared=True)
    try:
        yield
    finally:
        if shared:
            _exit_blas()
        for setter, count in zip(local, previous):
            setter(count)


def _local_setter(pool):
    """OpenBLAS's `openblas_set_num_threads_local` of `pool` (a ctypes function returning the
    previous count), or None for another BLAS or an OpenBLAS without it (before 0.3.27)."""
    if pool.internal_api != "openblas":
        return None
    setter = getattr(pool.dynlib, "openblas_set_num_threads_local", None)
    if setter is not None:
        setter.restype, setter.argtypes = ctypes.c_int, [ctypes.c_int]
    return setter


def _enter_blas(threads, only_shared=False):
    """Every BLAS pool (`only_shared`: those without a thread-local count) at `threads` threads,
    process-wide; counted, so that the last `_exit_blas` restores the counts before the first."""
    with _LOCK:
        pools = _pools("blas")
        if only_shared:
            pools = [pool for pool in pools if _local_setter(pool) is None]
        if _BLAS_SCOPE["depth"] == 0:  # (all of them: a later block may set the others)
            _BLAS_SCOPE["saved"] = [(pool, pool.get_num_threads()) for pool in _pools("blas")]
        _BLAS_SCOPE["depth"] += 1
        for pool in pools:
            if pool.get_num_threads() != threads:
                pool.set_num_threads(threads)


def _exit_blas():
    with _LOCK:
        _BLAS_SCOPE["depth"] -= 1
        if _BLAS_SCOPE["depth"] == 0:
            for pool, count in _BLAS_SCOPE["saved"]:
                if pool.get_num_threads() != count:
                    pool.set_num_threads(count)
            _BLAS_SCOPE["saved"] = None


@contextlib.contextmanager
def openmp_limited(threads):
    """The calling thread's OpenMP thread count (every loaded OpenMP runtime) at `threads` inside
    the block (`None`: unchanged), restored after it."""
    if threads is None:
        yield
        return
    saved = [(pool, pool.get_num_threads()) for pool in _pools("openmp")]
    for pool, count in saved:
        if count != threads:
            pool.set_num_threads(threads)
    try:
        yield
    finally:
        for pool, count in saved:
            if count != threads:
                pool.set_num_threads(count)


def lapack_limited(threads):
    """Every BLAS pool at `threads` threads, process-wide, inside the block (`None`: unchanged,
    a shared empty context, cheaper than a generator's), restored when the last such block of the
    process closes (`_enter_blas`'s counting): the scope of a compiled program whose LAPACK calls
    (XLA's CPU Cholesky calls SciPy's OpenBLAS) run on XLA's threads, not the caller's, so the
    calling thread's own count would not reach them. The block must wait for the program's
    results. It is set around the compiled call, not inside the program: host callbacks in the
    program would keep JAX's persistent cache from storing it and are refused under `vmap` of a
    `cond` (IO effects). Under the caller's own `jit` the scope is not applied (the caller owns
    the threads of its program)."""
    return _UNCHANGED if threads is None else _lapack_scope(threads)


_UNCHANGED = contextlib.nullcontext()


@contextlib.contextmanager
def _lapack_scope(threads):
    prepare()
    _enter_blas(threads)
    try:
        yield
    finally:
        _exit_blas()
