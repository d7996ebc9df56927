"""The package's layers hold: every import of one of its own modules goes to the same layer
or one below, no package imports another that imports it back, and every module imports
the package's modules at its top (only heavy third-party packages, as scipy.optimize,
matplotlib, mpmath, OpenMM or jax, are imported inside the functions that need them, so that
start-up stays light: tests/test_imports.py).

Layers, lowest first: the shared basics (``exceptions``, ``text``, ``units``,
``arguments``, ``lazy``, ``comparison``), ``files`` (method files, YAML, expressions),
``methods`` (tableaux and the library), ``core`` (the float analysis), ``systems`` (scenes,
coupled systems), ``api``,
``cli``, and the package root. ``reference`` (mpmath) sits beside them: it may import the
layers below ``api``, and only ``api``, ``cli``, the root and the tests import it.

A module that only some inputs reach is named at the top of its user with
``lazy_module("stepsafe.x.y")`` (:mod:`stepsafe.lazy`) and loaded on first use; it is held
to the same rules as an import (layers, no cycle between packages), except that it runs no
code when its user loads.

There are no exceptions.
"""

from __future__ import annotations

import ast
import functools
from pathlib import Path

PACKAGE = Path(__file__).resolve().parent.parent / "stepsafe"

#: The rank of each layer (a top-level module or package of stepsafe); an import may go to
#: an equal or lower rank. ``reference`` is checked separately (see :func:`allowed`).
RANK = {"_version": 0, "lazy": 0, "comparison": 0, "exceptions": 0, "text": 0, "units": 0,
        "arguments": 0, "files": 1, "methods": 2, "core": 3, "systems": 4, "reference": 4,
        "api": 5, "cli": 6, "": 7, "__main__": 7}

#: The layers that may import ``reference``.
REFERENCE_USERS = {"reference", "api", "cli", "", "__main__"}

def _module_name(path: Path) -> str:
    parts = list(path.relative_to(PACKAGE.parent).with_suffix("").parts)
    if parts[-1] == "__init__":
        parts = parts[:-1]
    return ".".join(parts)


def _layer(module: str) -> str:
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else ""


def _type_checking_nodes(tree: ast.AST) -> set[int]:
    """The nodes under ``if TYPE_CHECKING:`` (not imported when the program runs)."""
    out: set[int] = set()
    for node in ast.walk(tree):
        if isinstance(node, ast.If) and "TYPE_CHECKING" in ast.unparse(node.test):
            out.update(id(n) for n in ast.walk(node))
    return out


def _in_functions(tree: ast.AST) -> list[ast.AST]:
    """The nodes inside a function (run when it is called, not when the module loads)."""
    return [n for f in ast.walk(tree)
            if isinstance(f, (ast.FunctionDef, ast.AsyncFunctionDef, ast.Lambda))
            for n in ast.walk(f)]


@functools.cache
def _tree(path: Path) -> ast.Module:
    """The parsed module (parsed once: every test reads the same files, none changes them)."""
    return ast.parse(path.read_text(encoding="utf-8"))


def _imports(path: Path, top_only: bool = False, in_functions: bool = False
             ) -> list[tuple[str, int]]:
    """The package's own modules that ``path`` imports (at its top only, or inside its
    functions only), with their lines (``from stepsafe import x`` counts as the root, or as
    ``stepsafe.x`` when x is a module)."""
    tree = _tree(path)
    me = _module_name(path)
    package = me if path.name == "__init__.py" else me.rpartition(".")[0]
    skip = _type_checking_nodes(tree)
    nodes = tree.body if top_only else _in_functions(tree) if in_functions else \
        list(ast.walk(tree))
    out = []
    for node in nodes:
        if id(node) in skip:
            continue
        if isinstance(node, ast.Import):
            out += [(a.name, node.lineno) for a in node.names if a.name.split(".")[0]
                    == "stepsafe"]
        elif isinstance(node, ast.ImportFrom):
            name = node.module or ""
            if node.level:
                base = package.split(".")[:len(package.split(".")) - node.level + 1]
                name = ".".join(base + ([node.module] if node.module else []))
            if name.split(".")[0] != "stepsafe":
                continue
            for alias in node.names:
                full = f"{name}.{alias.name}"
                is_module = (PACKAGE.parent / (full.replace(".", "/") + ".py")).exists() or (
                    PACKAGE.parent / full.replace(".", "/")).is_dir()
                out.append((full if is_module else name, node.lineno))
    return out


def _is_lazy_call(node: ast.AST) -> bool:
    return isinstance(node, ast.Call) and (
        (isinstance(node.func, ast.Name) and node.func.id == "lazy_module")
        or (isinstance(node.func, ast.Attribute) and node.func.attr == "lazy_module"))


def _lazy_imports(path: Path) -> list[tuple[str, int]]:
    """The modules ``path`` names with ``lazy_module("...")`` (loaded on first use), with
    their lines; a name that is not a constant text is returned as ``"?"``."""
    tree = _tree(path)
    out = []
    for node in ast.walk(tree):
        if _is_lazy_call(node):
            args = node.args  # type: ignore[attr-defined]
            name = args[0].value if (len(args) == 1 and isinstance(args[0], ast.Constant)
                                     and isinstance(args[0].value, str)) else "?"
            out.append((name, node.lineno))
    return out


MODULES = sorted(PACKAGE.rglob("*.py"))


def allowed(importer: str, imported: str) -> bool:
    """Whether the layers let ``importer`` import ``imported``."""
    lower, upper = _layer(importer), _layer(imported)
    if lower == upper:
        return True
    if upper == "reference" and lower not in REFERENCE_USERS:
        return False
    return RANK[upper] <= RANK[lower]


def _violations() -> set[tuple[str, str, int]]:
    out = set()
    for path in MODULES:
        me = _module_name(path)
        for imported, line in _imports(path) + _lazy_imports(path):
            if not allowed(me, imported):
                out.add((me, imported, line))
    return out


def test_every_module_is_in_a_layer():
    layers = {_layer(_module_name(p)) for p in MODULES}
    assert layers <= set(RANK), layers - set(RANK)


def test_no_upward_import():
    found = sorted(f"{a}:{line} imports {b}" for a, b, line in _violations())
    assert not found, "imports against the layers:\n" + "\n".join(found)


def test_the_package_is_imported_at_module_top():
    """No function imports one of the package's own modules (a cycle or a slow start-up is
    fixed in the structure, by moving the shared piece down a layer or making a heavy
    third-party import lazy, not by hiding the import in a function)."""
    found = sorted(f"{_module_name(p)}:{line} imports {m} inside a function"
                   for p in MODULES for m, line in _imports(p, in_functions=True))
    assert not found, "\n".join(found)


def test_function_level_imports_are_told_from_top_level_ones():
    """The finder itself: an import in a function body (or a nested one) is found, one at
    the top of the module or in a class body is not."""
    tree = ast.parse("import a\nclass C:\n    import b\n    def f(self):\n        import c\n"
                     "def g():\n    def h():\n        from d import e\n    return h\n")
    found = {n.names[0].name if isinstance(n, ast.Import) else n.module
             for n in _in_functions(tree) if isinstance(n, (ast.Import, ast.ImportFrom))}
    assert found == {"c", "d"}


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one node (Tarjan)."""
    index: dict[str, int] = {}
    low: dict[str, int] = {}
    stack: list[str] = []
    on_stack: set[str] = set()
    out: list[list[str]] = []

    def visit(v: str) -> None:
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in graph.get(v, ()):
            if w not in index:
                visit(w)
                low[v] = min(low[v], low[w])
            elif w in on_stack:
                low[v] = min(low[v], index[w])
        if low[v] == index[v]:
            component = []
            while True:
                w = stack.pop()
                on_stack.discard(w)
                component.append(w)
                if w == v:
                    break
            if len(component) > 1:
                out.append(sorted(component))

    for v in sorted(graph):
        if v not in index:
            visit(v)
    return out


def test_cycle_finder_finds_a_cycle():
    """The cycle finder itself: a ring of three and a chain hanging off it."""
    assert _cycles({"a": {"b"}, "b": {"c"}, "c": {"a", "d"}, "d": set()}) == [["a", "b", "c"]]
    assert _cycles({"a": {"b"}, "b": set()}) == []


def test_no_import_cycle_between_packages():
    """Counting every import, at the top or in a function, and every module loaded on
    first use (``lazy_module``)."""
    graph: dict[str, set[str]] = {}
    for path in MODULES:
        me = _module_name(path)
        for imported, _ in _imports(path) + _lazy_imports(path):
            if _layer(imported) != _layer(me):
                graph.setdefault(_layer(me), set()).add(_layer(imported))
    assert _cycles(graph) == []


def test_no_import_cycle_between_modules_at_import_time():
    """The imports at the top of modules (those run when a module loads) form no cycle."""
    graph = {_module_name(p): {m for m, _ in _imports(p, top_only=True)} for p in MODULES}
    assert _cycles(graph) == []


def test_layer_rule_refuses_upward_and_reference_imports():
    """The rule itself: down and sideways pass; up, and the reference below api, fail."""
    assert allowed("stepsafe.cli.commands", "stepsafe.api.inputs")
    assert allowed("stepsafe.core.regions", "stepsafe.methods.tableaux")
    assert allowed("stepsafe.api.hmc", "stepsafe.reference.highprec")
    assert allowed("stepsafe.reference.verify", "stepsafe.core.transfer")
    assert not allowed("stepsafe.core.regions", "stepsafe.api.inputs")
    assert not allowed("stepsafe.methods.library", "stepsafe.systems.scene")
    assert not allowed("stepsafe.systems.scene", "stepsafe.reference.highprec")
    assert not allowed("stepsafe.files.yamlio", "stepsafe.methods.tableaux")


def test_modules_loaded_on_first_use_are_named_at_module_top():
    """Every ``lazy_module`` call is at module level (beside the imports, not in a
    function) and writes out the full name of a module of the package."""
    found = []
    for path in MODULES:
        me = _module_name(path)
        tree = _tree(path)
        in_functions = {id(n) for n in _in_functions(tree)}
        for node in ast.walk(tree):
            if _is_lazy_call(node) and id(node) in in_functions:
                found.append(f"{me}:{node.lineno}: lazy_module inside a function")
        for name, line in _lazy_imports(path):
            target = PACKAGE.parent / name.replace(".", "/")
            if not (name.startswith("stepsafe.") and (target.with_suffix(".py").exists()
                                                      or (target / "__init__.py").exists())):
                found.append(f"{me}:{line}: lazy_module({name!r}) names no module of the "
                             "package")
    assert not found, "\n".join(found)


def test_lazy_module_finder_finds_the_named_modules(tmp_path):
    """The finder itself: calls by name or through the module, with their lines; a name
    that is not written out is reported as unknown."""
    path = tmp_path / "m.py"
    path.write_text("from stepsafe.lazy import lazy_module\nimport stepsafe.lazy as lz\n"
                    "a = lazy_module('stepsafe.api.md')\nb = lz.lazy_module('stepsafe.cli.respa')\n"
                    "c = lazy_module(NAME)\n", encoding="utf-8")
    assert _lazy_imports(path) == [("stepsafe.api.md", 3), ("stepsafe.cli.respa", 4), ("?", 5)]


def test_a_lazy_module_to_a_higher_layer_is_an_upward_import():
    """The rule applied to modules loaded on first use: a core module may not name an api
    module, an api module may name a systems module."""
    assert not allowed("stepsafe.core.escalate", "stepsafe.api.linear")
    assert allowed("stepsafe.api.inputs", "stepsafe.systems.loader")
