"""Names that hold across processes, for `lieax._executable_store`'s keys: `describe` (values,
arrays by their bytes, lieax's own functions, classes and objects), `stable_repr` (a repr with
no address in it) and `jaxpr_fingerprint` (what a traced function computes). Each raises
`Undescribable` where it cannot name its argument that way; the store then keeps nothing.

lieax's own code is named by its module and name: the store's key holds a digest of lieax's
sources, so a change of that code changes every key.
"""

import enum
import functools
import hashlib
import pathlib
import re
import types

import jax
import numpy as np
from jax.extend import core as jax_core

_PACKAGE = pathlib.Path(__file__).resolve().parent
_CALLBACKS = {"pure_callback", "io_callback", "debug_callback", "debug_print"}
_FUNCTIONS = (types.FunctionType, types.MethodType, types.BuiltinFunctionType, functools.partial)


class Undescribable(Exception):
    """Something a program depends on that has no name across processes."""


def lieax_code(obj) -> bool:
    """Whether function or class `obj` is defined in lieax (its code is in the source digest)."""
    module = getattr(obj, "__module__", None) or ""
    return module == "lieax" or module.startswith("lieax.")


def describe(obj) -> str:
    """A text that names `obj` the same way in every process: plain values, containers of them,
    NumPy arrays (by a digest of their bytes), enums, and lieax's functions (with what their
    closures hold), classes and objects. `Undescribable` for anything else."""
    if obj is None or isinstance(obj, (bool, int, float, complex, str, bytes)):
        return f"{type(obj).__name__}:{obj!r}"
    if isinstance(obj, enum.Enum):
        return f"{describe(type(obj))}.{obj.name}"
    if isinstance(obj, jax.Array) and not isinstance(obj, jax.core.Tracer):
        obj = np.asarray(obj)
    if isinstance(obj, (np.ndarray, np.generic)):
        array = np.ascontiguousarray(obj)
        return f"array:{array.dtype.str}{array.shape}:{hashlib.sha256(array.data).hexdigest()}"
    if isinstance(obj, type):
        if lieax_code(obj) or obj.__module__ == "builtins":
            return f"class:{obj.__module__}.{obj.__qualname__}"
        raise Undescribable(f"class {obj.__module__}.{obj.__qualname__}")
    if isinstance(obj, functools.partial):
        return f"partial({describe(obj.func)},{describe(obj.args)},{describe(obj.keywords)})"
    if isinstance(obj, types.FunctionType):
        if not lieax_code(obj):
            raise Undescribable(f"function {obj.__module__}.{obj.__qualname__}")
        cells = tuple(c.cell_contents for c in obj.__closure__ or ())
        parts = (obj.__defaults__, obj.__kwdefaults__, cells)
        return f"function:{obj.__module__}.{obj.__qualname__}{describe(parts)}"
    if isinstance(obj, dict):
        items = sorted((describe(k), describe(v)) for k, v in obj.items())
        return "{" + ",".join(f"{k}:{v}" for k, v in items) + "}"
    if isinstance(obj, (set, frozenset)):
        return f"{describe(type(obj))}(" + ",".join(sorted(map(describe, obj))) + ")"
    if isinstance(obj, (tuple, list)):
        return f"{describe(type(obj))}(" + ",".join(map(describe, obj)) + ")"
    if lieax_code(type(obj)):
        slots = [s for c in type(obj).__mro__ for s in getattr(c, "__slots__", ())]
        fields = dict(getattr(obj, "__dict__", {}), **{s: getattr(obj, s) for s in slots})
        return f"{describe(type(obj))}{describe(fields)}"
    raise Undescribable(f"{type(obj).__module__}.{type(obj).__qualname__} object")


def stable_repr(obj) -> str:
    """`repr(obj)`, `Undescribable` where it shows an address (an object named by where it lives,
    not by what it is)."""
    text = repr(obj)
    found = re.search(r"<[^<>]* at 0x[0-9a-fA-F]+>", text)
    if found:
        raise Undescribable(found.group())
    return text


def jaxpr_fingerprint(closed_jaxpr) -> str:
    """What `closed_jaxpr` computes, named across processes: its printed program and a digest of
    its constants. `Undescribable` where the print leaves something out: a Python callback, or a
    parameter that is a function defined outside lieax (a custom derivative rule's body)."""
    _check_parameters(closed_jaxpr.jaxpr)
    digest = hashlib.sha256(str(closed_jaxpr.jaxpr).encode())
    for const in closed_jaxpr.consts:
        digest.update(describe(np.asarray(const)).encode())
    return "jaxpr:" + digest.hexdigest()


def _check_parameters(jaxpr):
    for eqn in jaxpr.eqns:
        if eqn.primitive.name in _CALLBACKS:
            raise Undescribable(f"a {eqn.primitive.name}")
        for value in eqn.params.values():
            _check_parameter(value)


def _check_parameter(value):
    if isinstance(value, jax_core.ClosedJaxpr):
        _check_parameters(value.jaxpr)
    elif isinstance(value, jax_core.Jaxpr):
        _check_parameters(value)
    elif isinstance(value, (tuple, list)):
        for item in value:
            _check_parameter(item)
    elif isinstance(value, _FUNCTIONS) or hasattr(value, "debug_info"):
        source = getattr(getattr(value, "debug_info", None), "func_src_info", None) or ""
        path = source.rpartition(" at ")[2].rpartition(":")[0]
        inside = path and pathlib.Path(path).resolve().is_relative_to(_PACKAGE)
        if not (inside or lieax_code(value)):
            raise Undescribable(f"a parameter {source or value!r}")
    elif callable(value) and not isinstance(value, type):
        stable_repr(value)  # an object that computes (a mesh, a callback): named by its repr
