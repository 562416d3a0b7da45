"""lieax's store of compiled programs: a second process runs a solver's compiled loop with no
trace, lowering or compilation (issue 30).

JAX's persistent compilation cache keys a program by its lowered module, so a process that finds
a program there has traced and lowered it first: 0.3-1.3 s for a factor graph's loop, more than
its warm solve. This store keys a compiled program by what determines it, known without a trace:

- the environment: lieax's sources and native library (a digest of their bytes), the versions of
  JAX and jaxlib, the device, the CPU's features, `XLA_FLAGS` and every JAX option (64-bit mode
  included);
- the program: its function's module and name, its compile options, a `fingerprint` of what it
  closes over (`lieax._describe.describe` of the static arguments by default: plain values and
  lieax's own functions and classes, whose code the source digest covers), and the arguments'
  tree and shapes, dtypes and weak types.

A factor graph's loop closes over the user's residual functions: their fingerprint is the jaxpr
of one instance (`lieax._describe.jaxpr_fingerprint`: the traced program and its constants'
bytes), which fixes everything the loop traces from them, since the loop differentiates and
batches that same computation (`lieax.factorgraph._fingerprint`). A jaxpr that holds a Python
callback or a custom derivative rule written outside lieax (whose body the jaxpr does not show)
is not described: that program is not stored, only compiled as usual (JAX's own cache still
applies). A call on other than concrete single-device arrays, or while JAX runs op by op or
checks for NaN, is not served either.

The store is on only after `enable` (`lieax.enable_compilation_cache` turns it on in
`<cache dir>/lieax-programs`). It is trusted like JAX's cache: loading a file runs its code.
Nothing is evicted (as JAX's cache by default): delete the directory to empty it.

What a loaded program needs, that tracing and lowering would have done:

- the runtime its custom calls use: jaxlib's LAPACK kernels and lieax's native library, whose
  handlers and BLAS pointers are set when a call to them is lowered (`before_loading`, by the
  target names in the program); else it crashes;
- host state its custom calls read: the native Cholesky's plan, registered when its analysis
  ends (`Programs`' `before_run` waits for it, after the load);
- a program compiled afresh when stored (`_fresh`): jaxlib 0.10's CPU executable that JAX read
  from its own cache serializes without its kernels. A loaded program's first run is awaited,
  and one that fails with NOT_FOUND is compiled again and its file rewritten; a file that fails
  to load is too.

Formats: one file per key, `<sha256>.bin`, the pickle of `(prefixes, serialized)`: the
`before_loading` target prefixes it needs and `jax.experimental.serialize_executable.serialize`
of the program; files are written whole (a temporary file, then a rename), so that processes
sharing the directory never read half a file.
"""

import contextlib
import functools
import hashlib
import os
import pathlib
import pickle
import platform
import tempfile
import threading
import types

import jax
import numpy as np
from jax._src import core as jax_internals
from jax.experimental import serialize_executable

try:  # JAX internals the store needs; a JAX that moved them runs without the store
    from jax._src import compiler as jax_compiler
    from jax._src import xla_bridge
    from jax._src.array import ArrayImpl
    from jax._src.config import trace_context as _trace_context
    from jax._src.lax.linalg import initialize_lapack as _initialize_lapack
except ImportError:  # pragma: no cover
    jax_compiler = xla_bridge = ArrayImpl = _trace_context = _initialize_lapack = None

from ._describe import Undescribable, describe, lieax_code

_PACKAGE = pathlib.Path(__file__).resolve().parent
_FRESH_LOCK = threading.Lock()
NOT_SERVED = object()  # `Programs.run`'s answer for a call the store does not serve
_directory = None  # the store's directory while it is on
_preparations = {}  # custom-call target prefix -> what a loaded program needs first
_loads = 0  # programs loaded from the store in this process


def enable(path: str | os.PathLike[str]) -> pathlib.Path:
    """Turns the store on in directory `path` (created if missing); returns it."""
    global _directory
    path = pathlib.Path(path).expanduser()
    path.mkdir(parents=True, exist_ok=True)
    _directory = path
    return path


def disable() -> None:
    """Turns the store off (programs already loaded stay in use)."""
    global _directory
    _directory = None


def directory() -> pathlib.Path | None:
    """The store's directory, or None while it is off."""
    return _directory


def loads() -> int:
    """How many programs this process loaded from the store (the benchmarks report it)."""
    return _loads


def before_loading(target_prefix: str, prepare) -> None:
    """Registers `prepare()`, called before a program that calls a custom-call target whose name
    starts with `target_prefix` is loaded from the store: the runtime that the program's lowering
    would have prepared (a native library's registration, its BLAS pointers)."""
    _preparations[target_prefix] = prepare


def jit(fun=None, *, fingerprint=None, **jit_options):
    """`jax.jit(fun, **jit_options)` whose compiled programs the store keeps while it is on (as
    a decorator too); a call on traced values, or while a program is staged, runs the plain
    `jax.jit`. `fingerprint` as `Programs` takes it."""
    if fun is None:
        return functools.partial(jit, fingerprint=fingerprint, **jit_options)
    jitted = jax.jit(fun, **jit_options)
    stored = Programs(jitted, fun, jit_options, fingerprint)

    @functools.wraps(fun)
    def call(*args, **kwargs):
        result = NOT_SERVED if traced(args, kwargs) else stored.run(args, kwargs)
        return jitted(*args, **kwargs) if result is NOT_SERVED else result

    call._cache_size = lambda: jitted._cache_size() + stored.compiled
    return call


def traced(args, kwargs) -> bool:
    """Whether a call on `args` and `kwargs` is transformed or staged: JAX's trace state is not
    clean (`jax._src.core.trace_state_clean`: a transformation or a staging is under way, which
    a traced argument implies; 0.3 us, where scanning the arguments' leaves for tracers took
    3 us of every warm solve). Where this JAX lacks it: an argument is traced, or JAX stages
    every operation, one on a constant too (which outside staging runs, compiling one small
    program)."""
    clean = getattr(jax_internals, "trace_state_clean", None)
    if clean is not None:
        return not clean()
    tracer = jax.core.Tracer  # pragma: no cover - older JAX
    if any(isinstance(leaf, tracer) for leaf in jax.tree.leaves((args, kwargs))):
        return True
    return isinstance(jax.lax.neg(np.float32(0)), tracer)


# ---- the environment: what every key shares ---------------------------------------------------


@functools.cache
def _environment() -> str:
    """What every key shares: a digest of lieax's sources and native library, the versions of
    JAX and jaxlib, the device, the CPU's architecture and features, `XLA_FLAGS` (once a
    process: 10-70 ms)."""
    digest = hashlib.sha256()
    for path in sorted(_PACKAGE.rglob("*")):
        if path.suffix in (".py", ".so", ".pyd") and "__pycache__" not in path.parts:
            digest.update(str(path.relative_to(_PACKAGE)).encode())
            digest.update(path.read_bytes())
    device = jax.devices()[0]
    flags = ""
    if os.path.exists("/proc/cpuinfo"):
        with open("/proc/cpuinfo", encoding="utf-8", errors="replace") as file:
            flags = next((line for line in file if line.startswith("flags")), "")
    parts = (
        digest.hexdigest(),
        jax.__version__,
        jax.lib.__version__,
        device.platform,
        device.device_kind,
        device.client.platform_version,
        platform.machine(),
        flags,
        os.environ.get("XLA_FLAGS", ""),
    )
    return repr(parts)


def _options() -> str:
    """JAX's options (what lowering reads), but the cache's own."""
    values = jax.config.values
    skip = ("compilation_cache", "persistent_cache", "log", "explain")
    return repr(sorted((k, repr(v)) for k, v in values.items() if not any(s in k for s in skip)))


# ---- the programs of one jitted function -------------------------------------------------------


class Programs:
    """The compiled programs of `jitted` (a `jax.jit` of `fun`) that the store serves, by call
    signature. `fingerprint()` names what `fun` computes beyond its arguments (default: `describe`
    of the static arguments, and `fun` is named by its module and name, which needs it to be
    lieax's and to close over nothing). `before_run()`, where given, is called before a loaded
    program first runs: host state its custom calls read, which its trace would have waited
    for (called after the load, so that the two overlap)."""

    def __init__(self, jitted, fun, jit_options, fingerprint=None, before_run=None):
        self.jitted = jitted
        self.fun = fun
        self.static = tuple(jit_options.get("static_argnames", ()))
        self.options = describe({k: v for k, v in jit_options.items() if k != "static_argnames"})
        self.fingerprint = fingerprint
        self.before_run = before_run
        self.found = {}  # signature -> compiled program, or None where not stored
        self.unproven = {}  # signature -> file, of the programs loaded and not yet run
        self.compiled = 0  # programs this process compiled (not loaded)

    def _split(self, kwargs):
        """`kwargs`' static arguments, sorted, and the others (what the compiled program takes)."""
        static = tuple(sorted((k, v) for k, v in kwargs.items() if k in self.static))
        return static, {k: v for k, v in kwargs.items() if k not in self.static}

    def run(self, args, kwargs):
        """The result of the call on `args` and `kwargs` (concrete) by the program from memory,
        the store, or compiled and stored; `NOT_SERVED` while the store is off or the call is
        not stored (the caller's `jax.jit` runs it then)."""
        if _directory is None or _trace_context is None or _checking():
            return NOT_SERVED
        static, dynamic = self._split(kwargs) if self.static and kwargs else ((), kwargs)
        leaves, treedef = jax.tree_util.tree_flatten((args, dynamic))
        avals = _avals(leaves)
        if avals is None:
            return NOT_SERVED
        # JAX's options that its own jit cache keys on (64-bit mode, promotion, ...)
        signature = (_trace_context(), static, treedef, avals)
        try:
            program = self.found[signature]
        except KeyError:
            program = self.found[signature] = self._program(signature, args, kwargs)
        except TypeError:  # an unhashable static argument: JAX's jit refuses it itself
            return NOT_SERVED
        if program is None:
            return NOT_SERVED
        if not self.unproven or signature not in self.unproven:
            return program(*args, **dynamic)
        if self.before_run is not None:
            self.before_run()
        try:  # a loaded program's first run, awaited (its errors come with its results)
            result = jax.block_until_ready(program(*args, **dynamic))
        except jax.errors.JaxRuntimeError as error:
            if "NOT_FOUND" not in str(error):
                raise
            # a file whose program lacks kernels (written by a lieax before this check): its
            # run stopped before any work; compiled afresh and stored again
            program = self.found[signature] = self._compile(self.unproven[signature], args, kwargs)
            result = program(*args, **dynamic)
        del self.unproven[signature]
        return result

    def _program(self, signature, args, kwargs):
        """The program of `signature` from the store, or compiled and stored; None where it is
        not stored (`Undescribable`)."""
        global _loads
        try:
            key = self._key(*signature[1:])
        except Exception:  # noqa: BLE001 - `Undescribable`, or a description that failed: the
            return None  # call runs as without the store (which never stops a call that works)
        path = _directory / f"{key}.bin"
        if path.exists():
            try:
                with open(path, "rb") as file:
                    needs, serialized = pickle.load(file)
                for prefix in needs:
                    _preparations[prefix]()
                program = serialize_executable.deserialize_and_load(*serialized)
                self.unproven[signature] = path
                _loads += 1
                return program
            except Exception:  # noqa: BLE001 - a damaged or foreign file: compiled again below
                pass
        return self._compile(path, args, kwargs)

    def _key(self, static, treedef, avals):
        _check_nodes(treedef)
        closure = self.fun.__closure__ if isinstance(self.fun, types.FunctionType) else None
        if self.fingerprint is not None:
            program = self.fingerprint()
        elif closure or not lieax_code(self.fun):  # named by its module and name: lieax's only
            raise Undescribable(f"{self.fun.__qualname__}: give a fingerprint")
        else:
            program = describe(static)
        parts = (
            _environment(),
            _options(),
            f"{self.fun.__module__}.{self.fun.__qualname__}",
            self.options,
            program,
            str(treedef),
            repr(avals),
        )
        return hashlib.sha256(repr(parts).encode()).hexdigest()

    def _compile(self, path, args, kwargs):
        """The program compiled afresh (not read from JAX's cache, see `_fresh`), written to
        `path` where it can be."""
        with _fresh() as fresh:
            compiled = self.jitted.lower(*args, **kwargs).compile()
        self.compiled += 1
        unloaded = getattr(compiled._executable, "_unloaded_executable", None)
        if not fresh or unloaded is None or unloaded.host_callbacks:
            return compiled  # kept in memory only (a Python callback cannot be stored)
        try:
            serialized = serialize_executable.serialize(compiled)
            # the targets' names are in the executable's bytes
            needs = [prefix for prefix in _preparations if prefix.encode() in serialized[0]]
            payload = pickle.dumps((needs, serialized))
            with tempfile.NamedTemporaryFile(dir=_directory, delete=False) as file:
                file.write(payload)
            os.replace(file.name, path)
        except (OSError, ValueError, NotImplementedError, pickle.PicklingError):
            pass  # an unwritable directory or an unserializable program: not stored
        return compiled


@contextlib.contextmanager
def _fresh():
    """Compilations inside skip JAX's persistent cache (neither read nor written); yields whether
    it could: jaxlib 0.10's CPU executable read from that cache serializes without its kernels,
    and a process that loaded such a file failed with "Function ... not found" at its first
    run. JAX has no option for one compilation: its cache key function is replaced while inside
    (a lock keeps the replacements of threads apart; another thread's compilation meanwhile
    skips the cache too, which only costs it time). A JAX without that function: False, and
    the program is not stored."""
    with _FRESH_LOCK:
        original = getattr(jax_compiler, "_get_cache_key", None)
        if original is not None:
            jax_compiler._get_cache_key = lambda *args, **kwargs: None
        try:
            yield original is not None
        finally:
            if original is not None:
                jax_compiler._get_cache_key = original


def _checking() -> bool:
    """Whether JAX runs op by op or checks for NaN or inf after each call (which a loaded
    program would skip): the store then stays out of the way."""
    config = jax.config
    return config.jax_disable_jit or config.jax_debug_nans or config.jax_debug_infs


def _avals(leaves):
    """`(shape, dtype, weak_type)` of each leaf, or None when one is not a concrete array on the
    default device (a traced, sharded or committed-elsewhere value: not stored). Every warm call
    pays for this: a concrete array's `aval` holds all three (0.1 us, where its `shape`, `dtype`
    and `weak_type` properties took 1 us), and where the process has one device (every backend's
    together) there is no other to be on (`devices()` took 0.9 us a leaf)."""
    device = None if _one_device() else jax.devices()[0]
    avals = []
    for leaf in leaves:
        if type(leaf) is ArrayImpl:  # a concrete array (a tracer is of another type)
            if device is not None and leaf.devices() != {device}:
                return None
            aval = leaf.aval
            avals.append((aval.shape, aval.dtype, aval.weak_type))
        elif isinstance(leaf, (np.ndarray, np.generic)):
            avals.append((leaf.shape, leaf.dtype, False))
        elif isinstance(leaf, (bool, int, float, complex)):
            avals.append(((), type(leaf).__name__, True))
        else:
            return None
    return tuple(avals)


@functools.cache
def _one_device() -> bool:
    """Whether the process has a single device over all of JAX's backends (fixed once they have
    started; a CPU array may be passed to a program of a GPU's, which `jax.jit` then runs on the
    CPU)."""
    return sum(len(backend.devices()) for backend in xla_bridge.backends().values()) == 1


def _check_nodes(treedef):
    """`Undescribable` unless every node type of `treedef` is a builtin or lieax's (a node type's
    flattening is code the key must cover)."""
    data = treedef.node_data()
    if data is not None:
        kind = data[0]
        if not (kind.__module__ == "builtins" or lieax_code(kind)):
            raise Undescribable(f"pytree node {kind.__module__}.{kind.__qualname__}")
    for child in treedef.children():
        _check_nodes(child)


# jaxlib's LAPACK kernels (their function pointers), set when a program using them is lowered:
# a program loaded without lowering needs them set first
before_loading("lapack_", _initialize_lapack)
