"""The package's shape holds: no import cycles, no other module's privates, no monkeypatching, small files; and
the tests mirror it (tests/<package>/ for afmid/<package>/, tests/cli/ for the top-level modules).

Read from the source with :mod:`ast` (nothing is imported), so a violation is named by file and line.
"""

from __future__ import annotations

import ast
from collections import defaultdict
from pathlib import Path

import pytest

TESTS = Path(__file__).resolve().parent
PACKAGE = TESTS.parent / "afmid"
MAX_LINES = 700


def _modules() -> dict[str, Path]:
    modules = {}
    for path in sorted(PACKAGE.rglob("*.py")):
        parts = path.relative_to(PACKAGE.parent).with_suffix("").parts
        name = ".".join(parts[:-1] if parts[-1] == "__init__" else parts)
        modules[name] = path
    return modules


MODULES = _modules()


def _tree(path: Path) -> ast.Module:
    """The module's syntax tree without its ``if TYPE_CHECKING:`` blocks (annotations are not imports)."""
    tree = ast.parse(path.read_text(), filename=str(path))
    for node in ast.walk(tree):
        if isinstance(node, ast.If) and "TYPE_CHECKING" in ast.unparse(node.test):
            node.body = [ast.Pass()]
    return tree


def _imports(name: str, path: Path):
    """(line, imported module, imported name or None) for every afmid import of module ``name``."""
    package = name.split(".") if path.name == "__init__.py" else name.split(".")[:-1]
    for node in ast.walk(_tree(path)):
        if isinstance(node, ast.ImportFrom):
            if node.level:
                base = package[: len(package) - node.level + 1]
                source = ".".join(base + ([node.module] if node.module else []))
            else:
                source = node.module or ""
            if source == "afmid" or source.startswith("afmid."):
                for alias in node.names:
                    yield node.lineno, source, alias.name
        elif isinstance(node, ast.Import):
            for alias in node.names:
                if alias.name.startswith("afmid"):
                    yield node.lineno, alias.name, None


def _import_graph() -> dict[str, set[str]]:
    graph = defaultdict(set)
    for name, path in MODULES.items():
        for _, source, imported in _imports(name, path):
            target = f"{source}.{imported}" if imported and f"{source}.{imported}" in MODULES else source
            if target != name and target in MODULES:
                graph[name].add(target)
    return graph


def test_no_module_imports_a_module_that_imports_it_back():
    graph = _import_graph()
    index, low, stack, on_stack, cycles = {}, {}, [], set(), []

    def visit(v):  # Tarjan's strongly connected components
        index[v] = low[v] = len(index)
        stack.append(v)
        on_stack.add(v)
        for w in sorted(graph[v]):
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
                cycles.append(sorted(component))

    for name in sorted(MODULES):
        if name not in index:
            visit(name)
    assert cycles == []


def test_no_module_imports_another_modules_private_names():
    offences = [f"{MODULES[name].relative_to(PACKAGE.parent)}:{line} imports {imported} from {source}"
                for name, path in MODULES.items() for line, source, imported in _imports(name, path)
                if imported and imported.startswith("_") and not imported.startswith("__") and source != name]
    assert offences == []


def test_no_module_assigns_attributes_of_another_module():
    """Monkeypatching at run time (``other_module.name = ...`` or ``setattr(other_module, ...)``) is how the
    diagnosis once swapped the fit's preparation; a module uses other modules' public functions only."""
    offences = []
    for name, path in MODULES.items():
        tree = _tree(path)
        aliases = {alias.asname or alias.name.split(".")[0] for node in ast.walk(tree)
                   if isinstance(node, (ast.Import, ast.ImportFrom)) for alias in node.names
                   if (alias.asname or alias.name).isidentifier()}
        imported_modules = {a for a in aliases if a in {m.rsplit(".", 1)[-1] for m in MODULES} | {"afmid"}}
        for node in ast.walk(tree):
            targets = node.targets if isinstance(node, ast.Assign) else [node.target] if isinstance(
                node, (ast.AugAssign, ast.AnnAssign)) else []
            for target in targets:
                if (isinstance(target, ast.Attribute) and isinstance(target.value, ast.Name)
                        and target.value.id in imported_modules):
                    offences.append(f"{path.relative_to(PACKAGE.parent)}:{node.lineno} assigns "
                                    f"{target.value.id}.{target.attr}")
            if (isinstance(node, ast.Call) and isinstance(node.func, ast.Name) and node.func.id == "setattr"
                    and node.args and isinstance(node.args[0], ast.Name) and node.args[0].id in imported_modules):
                offences.append(f"{path.relative_to(PACKAGE.parent)}:{node.lineno} setattr on {node.args[0].id}")
    assert offences == []


@pytest.mark.parametrize("name", sorted(MODULES))
def test_no_module_is_longer_than_the_limit(name):
    lines = MODULES[name].read_text().count("\n")
    assert lines <= MAX_LINES, f"{MODULES[name].relative_to(PACKAGE.parent)} has {lines} lines"


def test_the_tests_mirror_the_packages():
    """Every test module is in a folder named after a package of afmid (cli: the top-level modules), with an
    ``__init__.py`` (the folders are packages, so equal basenames cannot collide); only this file is at the top."""
    packages = {path.parent.name for path in PACKAGE.glob("*/__init__.py")} | {"cli"}
    offences = []
    for path in sorted(TESTS.rglob("test_*.py")):
        folder = path.parent.relative_to(TESTS)
        if folder == Path("."):
            if path.name != Path(__file__).name:
                offences.append(f"{path.name} is at the top of tests/")
        elif len(folder.parts) != 1 or folder.name not in packages:
            offences.append(f"tests/{folder}/{path.name}: tests/{folder} is not named after a package of afmid")
        elif not (path.parent / "__init__.py").exists():
            offences.append(f"tests/{folder} has no __init__.py")
    assert offences == []
