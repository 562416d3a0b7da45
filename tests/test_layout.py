"""The shape of the package, read from its source: lieax's modules import each other without a
circle (function-level imports included), no function runs past 120 lines, and code outside
`lieax.groups` reaches the groups through their public classes and `lieax.groups.kernels` only."""

import ast
import functools
import pathlib

import pytest

PACKAGE = pathlib.Path(__file__).resolve().parents[1] / "lieax"
MAX_FUNCTION_LINES = 120


def _module_name(path):
    parts = list(path.relative_to(PACKAGE.parent).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


SOURCES = {_module_name(p): p for p in sorted(PACKAGE.rglob("*.py"))}


@functools.cache
def trees():
    """`{module name: its parsed source}`, parsed when a test first needs it (not while pytest
    collects this file, on every worker)."""
    return {name: ast.parse(path.read_text(), str(path)) for name, path in SOURCES.items()}


def _imported_modules(name, packages, trees):
    """The modules of `trees` that module `name` imports anywhere in its body (a `from . import x`
    imports `x` if it is a module, its package otherwise)."""
    package = name if name in packages else name.rpartition(".")[0]
    for node in ast.walk(trees[name]):
        if isinstance(node, ast.ImportFrom):
            if node.level:
                base = package.split(".")[: len(package.split(".")) - node.level + 1]
                target = ".".join(base + ([node.module] if node.module else []))
            else:
                target = node.module or ""
            submodules = [f"{target}.{alias.name}" for alias in node.names]
            found = [m for m in submodules if m in trees]
            yield from found or ([target] if target in trees else [])
        elif isinstance(node, ast.Import):
            yield from (alias.name for alias in node.names if alias.name in trees)


def _cycles(trees, packages):
    """Strongly connected components of more than one module (Tarjan) of the import graph of
    `trees` (module name → AST); the `packages`' `__init__` are left out: a package re-exporting
    its modules is not a circle between them."""
    modules = set(trees) - set(packages)
    graph = {
        name: set(_imported_modules(name, packages, trees)) & modules - {name} for name in modules
    }
    index, low, stack, on_stack, components = {}, {}, [], set(), []

    def visit(v):
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in graph[v]:
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while not component or component[-1] != v:
                component.append(stack.pop())
                on_stack.discard(component[-1])
            if len(component) > 1:
                components.append(sorted(component))

    for v in graph:
        if v not in index:
            visit(v)
    return components


PACKAGES = {name for name, path in SOURCES.items() if path.name == "__init__.py"}


def test_no_import_circle():
    assert _cycles(trees(), PACKAGES) == []


def test_cycle_finder_sees_a_circle():
    """The check above can fail: two modules importing each other inside a function are found."""
    trees = {
        "pkg": ast.parse("from . import a"),
        "pkg.a": ast.parse("def f():\n    from . import b\n"),
        "pkg.b": ast.parse("from .a import f\n"),
        "pkg.c": ast.parse("from . import a\n"),
    }
    assert _cycles(trees, {"pkg"}) == [["pkg.a", "pkg.b"]]


@pytest.mark.parametrize("name", sorted(SOURCES))
def test_functions_are_short(name):
    long = [
        f"{node.name} ({node.end_lineno - node.lineno + 1} lines, line {node.lineno})"
        for node in ast.walk(trees()[name])
        if isinstance(node, ast.FunctionDef | ast.AsyncFunctionDef)
        and node.end_lineno - node.lineno + 1 > MAX_FUNCTION_LINES
    ]
    assert long == [], f"{name}: split by job"


@pytest.mark.parametrize("name", sorted(n for n in SOURCES if not n.startswith("lieax.groups")))
def test_groups_reached_through_their_declared_interface(name):
    """Outside `lieax.groups`: no private group module imported, no private constructor called
    (`kernels.element` wraps a kernel's output)."""
    private_imports = [
        f"line {node.lineno}"
        for node in ast.walk(trees()[name])
        if isinstance(node, ast.ImportFrom)
        and (
            (node.module or "").split(".")[-1].startswith("_")
            and "groups" in (node.module or "")
            or (node.module or "").endswith("groups")
            and any(alias.name.startswith("_") for alias in node.names)
        )
    ]
    private_calls = [
        f"line {node.lineno}"
        for node in ast.walk(trees()[name])
        if isinstance(node, ast.Attribute) and node.attr == "_wrap"
    ]
    assert private_imports == [] and private_calls == []
