"""`enable_compilation_cache`: JAX's persistent compilation cache, set for lieax's programs."""

import os
import pathlib

import jax

from . import _executable_store as executable_store


def default_cache_dir() -> pathlib.Path:
    """`$XDG_CACHE_HOME/lieax/jax`, or `~/.cache/lieax/jax` where `XDG_CACHE_HOME` is unset."""
    base = os.environ.get("XDG_CACHE_HOME") or os.path.join(os.path.expanduser("~"), ".cache")
    return pathlib.Path(base) / "lieax" / "jax"


def enable_compilation_cache(path: str | os.PathLike[str] | None = None) -> pathlib.Path:
    """Turns on JAX's persistent compilation cache and lieax's store of compiled solver loops,
    so that a second process loads the programs a first one compiled instead of compiling them
    again (XLA's compilation is most of a first call: seconds on a CPU).

    **Arguments:**

    - `path`: the cache directory (created if missing); by default `$XDG_CACHE_HOME/lieax/jax`,
      or `~/.cache/lieax/jax` where `XDG_CACHE_HOME` is unset.

    **Returns:** the directory, as a `pathlib.Path`.

    It sets JAX's options `jax_compilation_cache_dir` to `path`,
    `jax_persistent_cache_min_compile_time_secs` to 0 and
    `jax_persistent_cache_min_entry_size_bytes` to -1 (JAX's defaults skip programs that compile
    in under a second, which is most of lieax's: a solver's loop, the groups' small programs), for
    the whole process and every library in it, as setting them yourself would. Call it before the
    first computation: a later call also works (JAX's cache is reset to the new directory), but
    the programs this process compiled before it are not written (JAX keeps them in memory and
    does not compile them again). The cache is trusted: do not point it at a directory others
    may write to.

    What JAX cannot cache: a program that contains a Python host callback. Such a program is
    compiled in every process. In lieax today:

    - `lieax.icp` on a CPU with the default `search` and the normals and GICP covariances found
      with `search="kdtree"` (the default on a CPU) where the native library is not available
      (`lieax._native.available()`: they then use the host k-d tree); with it, those programs
      call its k-d tree by name and are cached (the registrations of `examples/icp_demo.py` and
      of the LiDAR pairs); `search="grid"` (and `"graph"` for the normals) is cached either way;
    - `lieax.factorgraph` with `linear_solver="cholesky"` and `lieax.graph.optimize` (the host
      multifrontal Cholesky) where the native library is not built or `LIEAX_NATIVE=0`: the
      solve loop (with the native library, its custom call is cached like the rest);
    - a solver's `throw=True` inside your own `jit` (the error is raised from a callback in the
      compiled program); outside `jit` the status is read after the program returns, which
      keeps it cacheable, and `throw=False` never adds a callback;
    - `verbose=True` (the progress is printed from a callback).

    Every other program (groups, `lieax.jacobian`, `lstsq.least_squares`, IMU preintegration,
    `factorgraph` with the dense or CG solvers) is cached.

    JAX finds a program in its cache by the program itself, so a second process still traces
    and lowers it first: 0.3-1.3 s for a factor graph's solve loop, more than the warm solve.
    lieax's store (`lieax._executable_store`, in `path / "lieax-programs"`) keeps the compiled
    loops of `FactorGraph.solve` (and so `lieax.graph.optimize`, bundle adjustment and the IMU
    smoother), of ICP and GICP and their normals and covariances, and IMU preintegration, each
    under a key of what determines it, known without tracing: lieax's source and native
    library, the versions of JAX and jaxlib, the device and CPU, `XLA_FLAGS` and JAX's options,
    the static options, the arguments' shapes and dtypes, the graph's structure, and your
    residual functions by the jaxpr of one instance (the traced program and its constants).
    A second process loads the loop and runs it with no trace at all (the docs' factor graph
    0.8 -> 0.3 s; the ICP demo 0.65 -> 0.3 s). A loop whose factors hold a Python callback or
    a custom derivative rule written outside lieax (whose body a jaxpr's print does not show),
    or takes a retraction or loss written outside lieax, is not stored: JAX's cache serves it
    as before.
    """
    path = pathlib.Path(default_cache_dir() if path is None else path).expanduser()
    path.mkdir(parents=True, exist_ok=True)
    jax.config.update("jax_persistent_cache_min_compile_time_secs", 0.0)
    jax.config.update("jax_persistent_cache_min_entry_size_bytes", -1)
    jax.config.update("jax_compilation_cache_dir", str(path))
    from jax.experimental.compilation_cache import compilation_cache

    compilation_cache.reset_cache()  # a cache already opened (or found off) takes the new path
    executable_store.enable(path / "lieax-programs")
    return path
