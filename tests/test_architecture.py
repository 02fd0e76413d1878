"""The shape of the package (DESIGN.md, STYLE.md): layers whose imports point downwards only,
modules of one concept (under ~600 lines), functions under ~80 lines, a package root that only
re-exports, and the equinox enumeration internals read in one place only."""

from __future__ import annotations

import ast
import pathlib

import pytest

PACKAGE = pathlib.Path(__file__).resolve().parent.parent / "rbo_jax"

# Bottom to top. A module may import from its own layer's package folder and from lower layers.
LAYERS = [
    ("_custom_types", "_elementary", "_progress", "_version"),
    ("_cache", "_callables"),
    ("_precision", "_devices", "_enumeration", "_programs", "_lazy"),
    ("_sharding",),
    ("_validation",),
    ("kinematics",),
    ("inertia", "analytic"),
    ("foundations",),
    ("loads",),
    ("mechanics",),
    ("models",),
    ("model", "solvers"),
    ("problems",),
    ("trajectory",),
    ("integrate",),
    ("simulate", "ensemble"),
    ("stability", "precession"),
    ("maps", "continuation"),
    ("fitting", "bifurcation"),
    ("lattice",),
    ("motion",),
    ("batch",),
    ("plotting",),
    ("app",),
    ("__main__",),  # python -m rbo_jax: the command
]
LAYER = {name: i for i, names in enumerate(LAYERS) for name in names}
ROOT = "<rbo_jax>"  # the package root re-exports every layer: only the top layer imports it
LAYER[ROOT] = LAYER["app"] - 1
MAX_MODULE_LINES = 600
MAX_FUNCTION_LINES = 80


def _modules():
    return sorted(
        p for p in PACKAGE.rglob("*.py") if p.name != "__init__.py" or p.parent != PACKAGE
    )


def _top(path: pathlib.Path) -> str:
    """The top-level unit of rbo_jax a file belongs to (module or package folder)."""
    rel = path.relative_to(PACKAGE).parts
    return rel[0][:-3] if rel[0].endswith(".py") else rel[0]


def _is_unit(name: str) -> bool:
    return (PACKAGE / f"{name}.py").exists() or (PACKAGE / name / "__init__.py").exists()


def _imported_units(path: pathlib.Path) -> set[str]:
    tree = ast.parse(path.read_text())
    depth = len(path.relative_to(PACKAGE).parts) - 1  # folders below rbo_jax
    units = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.ImportFrom):
            if node.level == 0:
                parts = (node.module or "").split(".")
                if parts[0] == "rbo_jax" and len(parts) > 1:
                    units.add(parts[1])
                elif parts[0] == "rbo_jax":
                    units.add(ROOT)
                continue
            if node.level <= depth:  # inside the same package folder
                continue
            target = (node.module or "").split(".")[0]
            if target:
                units.add(target)
            else:  # `from .. import name`: a module of the package, or a re-export of the root
                units.update(a.name if _is_unit(a.name) else ROOT for a in node.names)
        elif isinstance(node, ast.Import):
            for a in node.names:
                parts = a.name.split(".")
                if parts[0] == "rbo_jax" and len(parts) > 1:
                    units.add(parts[1])
    return units


def test_every_unit_has_a_layer():
    units = {_top(p) for p in PACKAGE.rglob("*.py") if p != PACKAGE / "__init__.py"}
    assert units <= set(LAYER), f"place {sorted(units - set(LAYER))} in LAYERS"
    assert _top(PACKAGE / "app" / "cli" / "_fit.py") == "app"


@pytest.mark.parametrize("path", _modules(), ids=lambda p: str(p.relative_to(PACKAGE)))
def test_imports_point_downwards(path):
    me = _top(path)
    for unit in _imported_units(path):
        if unit == me or unit == "__version__":
            continue
        assert unit in LAYER, (path, unit)
        assert LAYER[unit] < LAYER[me], (
            f"{path.relative_to(PACKAGE)} (layer {LAYER[me]}, {me}) imports {unit} "
            f"(layer {LAYER[unit]}): imports must point downwards"
        )


@pytest.mark.parametrize("path", _modules(), ids=lambda p: str(p.relative_to(PACKAGE)))
def test_modules_and_functions_are_small(path):
    text = path.read_text()
    assert len(text.splitlines()) <= MAX_MODULE_LINES, path
    for node in ast.walk(ast.parse(text)):
        if isinstance(node, (ast.FunctionDef, ast.AsyncFunctionDef)):
            length = node.end_lineno - node.lineno + 1
            doc = node.body[0]
            if isinstance(doc, ast.Expr) and isinstance(doc.value, ast.Constant):
                length -= doc.end_lineno - doc.lineno + 1  # the code, not its documentation
            assert length <= MAX_FUNCTION_LINES, (
                f"{path.name}:{node.lineno} {node.name} is {length} lines"
            )


def _absolute_imports(path: pathlib.Path):
    """``(module, name)`` of every ``from module import name`` in ``path``, ``module``
    absolute."""
    package = list(path.relative_to(PACKAGE.parent).with_suffix("").parts)[:-1]
    for node in ast.walk(ast.parse(path.read_text())):
        if isinstance(node, ast.ImportFrom):
            base = package[: len(package) - node.level + 1] if node.level else []
            module = ".".join(base + ([node.module] if node.module else []))
            for alias in node.names:
                yield module, alias.name


def test_no_private_name_is_imported_from_another_package():
    """A package uses another package's public names only (issue 49 D): no ``_name`` and no
    ``_module`` of ``rbo_jax.other`` is imported. A helper that two packages need has a home of
    its own (a module of the lowest layers, ``rbo_jax._validation``, ``rbo_jax._programs``), or
    is an interface of its package (``rbo_jax.fitting.constants``)."""
    found = []
    for path in _modules():
        me = _top(path)
        for module, name in _absolute_imports(path):
            parts = f"{module}.{name}".split(".")
            if parts[0] != "rbo_jax" or len(parts) < 3 or parts[1] == me:
                continue
            if not (PACKAGE / parts[1] / "__init__.py").exists():
                continue  # a module of the package root: a helper's own home
            if any(p.startswith("_") and not p.startswith("__") for p in parts[2:]):
                found.append(f"{path.relative_to(PACKAGE)}: {module}.{name}")
    assert not found, found


def test_the_package_root_only_re_exports():
    tree = ast.parse((PACKAGE / "__init__.py").read_text())
    for node in tree.body:
        if isinstance(node, (ast.Import, ast.ImportFrom)):
            continue
        if isinstance(node, ast.Expr) and isinstance(node.value, (ast.Constant, ast.Call)):
            continue  # the docstring, and the call that enables float64
        if isinstance(node, ast.Assign) and [ast.unparse(t) for t in node.targets] == [
            "__version__"
        ]:
            continue
        if (
            isinstance(node, ast.Assign)
            and isinstance(node.value, ast.Call)
            and [ast.unparse(t) for t in node.targets] == ["(__getattr__, __dir__, __all__)"]
            and ast.unparse(node.value.func) == "_lazy.attach"
        ):
            continue  # the re-exports, loaded on first use: a table module -> names
        raise AssertionError(f"rbo_jax/__init__.py line {node.lineno}: only re-exports belong here")


def test_enumeration_internals_are_read_in_one_module():
    for path in PACKAGE.rglob("*.py"):
        if path.name == "_enumeration.py":
            continue
        text = path.read_text()
        for internal in ("_name_to_item", "._value", "._enumeration"):
            assert internal not in text, f"{path.relative_to(PACKAGE)} reads {internal}"


def _module_name(path: pathlib.Path) -> str:
    """``rbo_jax.app.cli._lattice`` for its file; a package by its folder."""
    parts = list(path.relative_to(PACKAGE.parent).with_suffix("").parts)
    return ".".join(parts[:-1] if parts[-1] == "__init__" else parts)


def _import_graph() -> dict[str, set[str]]:
    """Every module of rbo_jax -> the modules of rbo_jax it imports, anywhere in its source (at
    the top, inside functions, under ``TYPE_CHECKING``). ``from P import x`` names the module
    ``P.x`` where there is one, else ``P`` itself (a package's ``__init__``)."""
    modules = {_module_name(p): p for p in PACKAGE.rglob("*.py")}
    graph = {}
    for me, path in modules.items():
        package = me if path.name == "__init__.py" else me.rpartition(".")[0]
        targets = set()
        for node in ast.walk(ast.parse(path.read_text())):
            if isinstance(node, ast.Import):
                names = [a.name for a in node.names]
            elif isinstance(node, ast.ImportFrom):
                base = node.module or ""
                if node.level:  # relative: up from the module's package
                    up = package.split(".")[: len(package.split(".")) - node.level + 1]
                    base = ".".join(up + ([base] if base else []))
                names = [
                    f"{base}.{a.name}" if f"{base}.{a.name}" in modules else base
                    for a in node.names
                ]
            else:
                continue
            for name in names:
                while name and name not in modules:  # an attribute of a module: the module
                    name = name.rpartition(".")[0]
                if name and name != me:
                    targets.add(name)
        graph[me] = targets
    return graph


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one module (Tarjan's algorithm)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    found = []

    def visit(v):
        index[v] = low[v] = len(index)
        stack.append(v)
        for w in sorted(graph[v]):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while not component or component[-1] != v:
                component.append(stack.pop())
            if len(component) > 1:
                found.append(sorted(component))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return found


def test_no_modules_import_each_other():
    """The modules of rbo_jax import each other in no circle, however long and wherever the
    import stands (a function-level import closes a circle too): what two modules both need
    belongs in a module below them."""
    graph = _import_graph()
    assert "rbo_jax.app.cli._samples" in graph["rbo_jax.app.cli._lattice"]
    assert "rbo_jax.integrate.dop853" in graph["rbo_jax.lattice._integrate"]
    assert _cycles(graph) == []
    assert _cycles({"a": {"b"}, "b": {"c"}, "c": {"a"}, "d": {"a"}}) == [["a", "b", "c"]]
