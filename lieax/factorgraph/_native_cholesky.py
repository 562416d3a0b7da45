"""The numeric phase of the multifrontal `CholeskyPlan` in C++ (`csrc/cholesky.cc`), called from
compiled programs as the XLA FFI target `lieax_cholesky_solve`, which JAX's persistent
compilation cache can keep (a program holding the host callback of `_multifrontal.cholesky_solve`'s
NumPy path is recompiled in every process).

The plan is large host data that differs in nothing across processes but its address, so the
program names it by a key: `analysis_key`, a 63-bit digest of the pattern and the analysis
options, an attribute of the custom call. `register` hands the analysis (order, fronts, tree)
to the library's registry under that key when `CholeskyPlan.analyze` ends; the registration
holds as long as the plan object lives (a `weakref.finalize` releases it; plans of one pattern
share the key, counted). A program loaded from the cache in a second process finds its plan
because that process analyses the same pattern (`FactorGraph.solve` starts the analysis before
it calls the loop, and a loop that `lieax._executable_store` loaded, not traced, waits for it
before it first runs: `_solve.make_loop`'s `ready`).

A solve traced with a plan given as a function (`Layout.plan`, whose analysis
`Layout.start_plan` began in the background) waits for the analysis at trace time and names its
key, so the plan is registered before the program runs. A key not registered when the program
runs (its plan was collected, or never analysed in this process) is an error naming the key, not
a crash.
"""

import ctypes
import functools
import hashlib
import threading
import weakref

import jax
import numpy as np

from .. import _executable_store as executable_store
from .. import _native, _threads

TARGET = "lieax_cholesky_solve"
KEYED_TARGET = "lieax_cholesky_solve_keyed"
# SciPy's BLAS and LAPACK functions handed to the library, in its order (see `csrc/cholesky.cc`)
_FUNCTIONS = (("lapack", "potrf"), ("blas", "trsm"), ("blas", "syrk"), ("blas", "trsv"))


def available() -> bool:
    """Whether the native library is loaded (see `lieax._native`) and given SciPy's BLAS."""
    return _initialized() is not None


_INIT_LOCK = threading.Lock()  # the analysis thread and the caller's may both come first


def _initialized():
    """The library after `LieaxCholeskyInit` (the BLAS and LAPACK function pointers that SciPy's
    `cython_blas` / `cython_lapack` export, as jaxlib takes its own), or None; once."""
    with _INIT_LOCK:
        return _initialize()


# a stored program that calls the library (`lieax._executable_store`) needs its BLAS pointers
executable_store.before_loading("lieax_cholesky", _initialized)


@functools.cache
def _initialize():
    lib = _native.library()
    if lib is None:
        return None
    from scipy.linalg import cython_blas, cython_lapack

    modules = {"blas": cython_blas.__pyx_capi__, "lapack": cython_lapack.__pyx_capi__}
    pointers = {
        prefix: (ctypes.c_void_p * len(_FUNCTIONS))(
            *(_capsule_pointer(modules[kind][prefix + name]) for kind, name in _FUNCTIONS)
        )
        for prefix in ("d", "s")
    }
    lib.LieaxCholeskyInit(pointers["d"], pointers["s"])
    int64_p = ctypes.POINTER(ctypes.c_int64)
    lib.LieaxCholeskyRegister.argtypes = (
        [ctypes.c_int64] * 4 + [int64_p] * 3 + [ctypes.c_int64, *[int64_p] * 6, ctypes.c_int]
    )
    for name in ("Release", "References"):
        getattr(lib, "LieaxCholesky" + name).argtypes = [ctypes.c_int64]
    lib.LieaxCholeskySetThreads.argtypes = [ctypes.c_int]
    _threads.on_change(lambda threads: lib.LieaxCholeskySetThreads(threads or 0))
    return lib


def _capsule_pointer(capsule):
    get_name = ctypes.pythonapi.PyCapsule_GetName
    get_name.restype, get_name.argtypes = ctypes.c_char_p, [ctypes.py_object]
    get_pointer = ctypes.pythonapi.PyCapsule_GetPointer
    get_pointer.restype, get_pointer.argtypes = ctypes.c_void_p, [ctypes.py_object, ctypes.c_char_p]
    return get_pointer(capsule, get_name(capsule))


def analysis_key(pattern, options):
    """The plan key of `pattern` analysed with `options` (a tuple of the analysis' arguments): a
    63-bit BLAKE2b digest of the block count and size, the pairs and the options."""
    h = hashlib.blake2b(digest_size=8)
    h.update(f"{pattern.num_blocks},{pattern.block_size},{options!r}".encode())
    for a in (pattern.rows, pattern.cols):
        h.update(np.ascontiguousarray(a, dtype=np.int64).tobytes())
    return int.from_bytes(h.digest(), "little") & ((1 << 63) - 1)


def register(plan, key, symbolic, single_thread):
    """Registers `symbolic` (a `_cholesky_analysis._Symbolic`) of `plan` under `key` for as long as `plan`
    lives. `single_thread`: the library's BLAS calls for it run on the calling thread (OpenBLAS's
    thread-local count, set and restored around each call), else on lieax's setting
    (`lieax.set_threads`; `None`: the library's own), as `_multifrontal._host_solve` does."""
    lib = _initialized()
    pattern = plan.pattern

    def ragged(lists):
        start = np.zeros(len(lists) + 1, np.int64)
        start[1:] = np.cumsum([len(a) for a in lists])
        flat = np.concatenate([np.asarray(a, np.int64) for a in lists])
        return start, np.ascontiguousarray(flat, dtype=np.int64)

    arrays = [
        np.ascontiguousarray(a, dtype=np.int64)
        for a in (pattern.rows, pattern.cols, symbolic.order)
    ]
    fronts = [ragged(x) for x in (symbolic.pivots, symbolic.updates, symbolic.children)]
    pointer = lambda a: a.ctypes.data_as(ctypes.POINTER(ctypes.c_int64))
    status = lib.LieaxCholeskyRegister(
        key, pattern.num_blocks, pattern.block_size, pattern.num_pairs,
        *(pointer(a) for a in arrays), len(symbolic.pivots),
        *(pointer(a) for start_flat in fronts for a in start_flat), int(single_thread),
    )  # fmt: skip
    if status != 0:
        raise RuntimeError(
            "lieax multifrontal Cholesky: the native library refused the analysis of a "
            f"{pattern.num_blocks}-block pattern as inconsistent (a bug in the analysis)."
        )
    weakref.finalize(plan, lib.LieaxCholeskyRelease, key)


def references(key):
    """The live plan objects registered under `key` (tests)."""
    return int(_initialized().LieaxCholeskyReferences(key))


def scopes_threads():
    """Whether the library found OpenBLAS's thread-local count next to SciPy's BLAS (else the
    BLAS's own setting holds for its calls)."""
    return bool(_initialized().LieaxCholeskyScopesThreads())


def solve(key, diag, off, rhs):
    r"""$H^{-1}$ `rhs` by the registered plan `key`, inside JAX; under `vmap` one call for the
    batch (its systems factored one after another)."""
    call = jax.ffi.ffi_call(
        TARGET, jax.ShapeDtypeStruct(rhs.shape, rhs.dtype), vmap_method="broadcast_all"
    )
    return call(diag, off, rhs, key=np.int64(key))


def key_words(key):
    """The operand of `solve_keyed` naming the plan `key`: its low and high 32-bit words, uint32
    (an operand of any JAX mode, where an int64 one would be cut to 32 bits without x64)."""
    return np.asarray([key & 0xFFFFFFFF, key >> 32], np.uint32)


def solve_keyed(words, diag, off, rhs):
    r"""$H^{-1}$ `rhs` by the registered plan named at run time by `words` (`key_words`, an
    operand, so that one compiled program serves every plan of its shapes: a bucketed factor
    graph's); `off` may hold more pair blocks than the plan has, its first `num_pairs` the
    plan's (the rest are not read)."""
    call = jax.ffi.ffi_call(
        KEYED_TARGET, jax.ShapeDtypeStruct(rhs.shape, rhs.dtype), vmap_method="broadcast_all"
    )
    return call(words, diag, off, rhs)
