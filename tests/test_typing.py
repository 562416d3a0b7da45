"""lieax ships `py.typed`: the public callables of the modules in `ANNOTATED` carry type hints on
every parameter and on their result, so that a type checker sees lieax's names instead of `Any`.

The public API is what a user reaches: the names in `__all__` of `lieax` and of its public
subpackages and modules, and the public methods, properties and operators of the classes among
them. Each callable belongs to the module that defines it (`__module__`); an entry of
`ANNOTATED` covers that module or package and everything under it. The modules not yet listed
are the next to annotate: add them here as they are.

That the hints are also true (a checker reports no false error on a user's script) is checked
with mypy on `tests/typecheck/user_script.py` (see its docstring); this file needs no checker.
"""

import importlib
import inspect
import pkgutil
import typing

import pytest

import lieax

ANNOTATED = [
    "lieax._align",
    "lieax._compilation_cache",
    "lieax._threads",
    "lieax.autodiff",
    "lieax.ba",
    "lieax.cameras",
    "lieax.conventions",
    "lieax.groups",
    "lieax.io",
    "lieax.lstsq._losses",
    "lieax.optax",
    "lieax.sharding",
]

# the special methods that are part of a class's API (operators, construction, calls)
_PUBLIC_SPECIAL = {"__init__", "__call__", "__matmul__", "__getitem__"}


def _public_modules():
    """`lieax` and its public subpackages and modules (no leading underscore)."""
    names = [m.name for m in pkgutil.iter_modules(lieax.__path__) if not m.name.startswith("_")]
    return [lieax, *(importlib.import_module(f"lieax.{name}") for name in names)]


def _members(cls):
    """`(name, function)` of the public methods, properties and operators `cls` defines."""
    for name, value in vars(cls).items():
        if name.startswith("_") and name not in _PUBLIC_SPECIAL:
            continue
        if isinstance(value, property):
            value = value.fget
        elif isinstance(value, (classmethod, staticmethod)):
            value = value.__func__
        if inspect.isfunction(value):
            yield f"{cls.__name__}.{name}", value


def _public_callables():
    """`{qualified name: (defining module, function)}` of lieax's public API (module docstring)."""
    found = {}
    for module in _public_modules():
        for name in getattr(module, "__all__", ()):
            obj = getattr(module, name)
            if inspect.isclass(obj):
                for member, function in _members(obj):
                    found.setdefault(f"{obj.__module__}.{member}", (obj.__module__, function))
            elif inspect.isfunction(obj) or inspect.isfunction(getattr(obj, "__wrapped__", None)):
                found.setdefault(f"{obj.__module__}.{obj.__name__}", (obj.__module__, obj))
    return found


def _missing_annotations(function, qualified_name):
    """The parameters of `function` without a hint, and `->` when its result has none; an
    overloaded function is judged by its overloads (its implementation is never seen by a
    checker)."""
    missing = []
    for variant in typing.get_overloads(function) or [function]:
        signature = inspect.signature(getattr(variant, "__func__", variant))  # a classmethod's
        for name, parameter in signature.parameters.items():
            if name in ("self", "cls") or parameter.annotation is not inspect.Parameter.empty:
                continue
            if parameter.kind not in (parameter.VAR_POSITIONAL, parameter.VAR_KEYWORD):
                missing.append(name)
        initializer = qualified_name.endswith(".__init__")
        if signature.return_annotation is inspect.Signature.empty and not initializer:
            missing.append("->")
    return sorted(set(missing))


PUBLIC = _public_callables()


def _in(module, prefix):
    return module == prefix or module.startswith(prefix + ".")


@pytest.mark.parametrize("prefix", ANNOTATED)
def test_public_callables_are_annotated(prefix):
    covered = {name: f for name, (module, f) in PUBLIC.items() if _in(module, prefix)}
    assert covered, f"{prefix} defines no public callable: a misspelled entry of ANNOTATED?"
    unannotated = {
        name: missing
        for name, f in covered.items()
        if (missing := _missing_annotations(inspect.unwrap(f), name))
    }
    assert unannotated == {}, f"public callables of {prefix} without type hints: {unannotated}"
