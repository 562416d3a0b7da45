"""The native library: XLA FFI handlers registered with JAX by name.

A compiled program that calls a Python host callback is never written to JAX's persistent
compilation cache; one that calls a custom call registered by name is, like JAX's own LAPACK
calls. So the default paths' host work (the k-d tree of `lieax.icp`, the multifrontal Cholesky of
`lieax.factorgraph`) lives in `lieax._lieax_native`, a C++ library that `pip install` builds from
`csrc/` (see `setup.py`), loaded with `ctypes` and registered through `jax.ffi`.

The library is optional: `available()` is False where it was not built (no compiler) or where
the environment variable `LIEAX_NATIVE=0` turns it off, and lieax then uses its host-callback
versions of the same algorithms.
"""

import ctypes
import functools
import importlib.util
import os

import jax

from . import _executable_store as executable_store
from . import _threads

# handler symbol in the library -> name of the custom-call target registered with JAX
_TARGETS = {
    "LieaxProbe": "lieax_probe",
    "LieaxCholeskySolve": "lieax_cholesky_solve",
    "LieaxCholeskySolveKeyed": "lieax_cholesky_solve_keyed",
    "LieaxKdtreeBuild": "lieax_kdtree_build",
    "LieaxKdtreeNearest": "lieax_kdtree_nearest",
    "LieaxKdtreeTrack": "lieax_kdtree_track",
    "LieaxKdtreeSpacing": "lieax_kdtree_spacing",
    "LieaxKdtreeNeighbours": "lieax_kdtree_neighbours",
    "LieaxKdtreeCovariances": "lieax_kdtree_covariances",
}


@functools.cache
def library():
    """The loaded library with its targets registered, or None (see the module docstring)."""
    if os.environ.get("LIEAX_NATIVE", "1") == "0":
        return None
    spec = importlib.util.find_spec("lieax._lieax_native")
    if spec is None or spec.origin is None:
        return None
    lib = ctypes.CDLL(spec.origin)
    for symbol, target in _TARGETS.items():
        jax.ffi.register_ffi_target(target, jax.ffi.pycapsule(getattr(lib, symbol)), platform="cpu")
    lib.LieaxSetThreads.argtypes = [ctypes.c_int]
    _threads.on_change(lambda threads: lib.LieaxSetThreads(threads or 0))  # the k-d tree's cap
    return lib


executable_store.before_loading("lieax_", library)  # a stored program's targets, registered


def available() -> bool:
    """Whether the native library is built, enabled and registered."""
    return library() is not None
