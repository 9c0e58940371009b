"""The package's shape holds: the layers of docs/architecture.md as a contract (no import cycle between modules
or between folders, no import from a lower layer into a higher one), no other module's privates, no
monkeypatching, small files; and the tests mirror it (tests/<package>/ for afmid/<package>/, tests/cli/ for the
top-level modules).

Read from the source with :mod:`ast` (nothing is imported), so a violation is named by file and line. Every
import counts: module level, inside a function (a lazy import still ties the two modules at run time) and under
``if TYPE_CHECKING:`` (an annotation still names the other module's type, so the layers must hold for it too).
"""

from __future__ import annotations

import ast
import re
from collections import defaultdict
from pathlib import Path


TESTS = Path(__file__).resolve().parent
PACKAGE = TESTS.parent / "afmid"


def _modules() -> dict[str, Path]:
    modules = {}
    for path in sorted(PACKAGE.rglob("*.py")):
        parts = path.relative_to(PACKAGE.parent).with_suffix("").parts
        name = ".".join(parts[:-1] if parts[-1] == "__init__" else parts)
        modules[name] = path
    return modules


MODULES = _modules()


def _tree(path: Path) -> ast.Module:
    """The module's whole syntax tree: ``TYPE_CHECKING`` blocks and function bodies included."""
    return ast.parse(path.read_text(), filename=str(path))


def _imports(name: str, path: Path):
    """(line, imported module, imported name or None) for every afmid import of module ``name``, wherever it
    stands (module level, a function, an ``if TYPE_CHECKING:`` block)."""
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


def _import_edges() -> dict[tuple[str, str], list[int]]:
    """(importing module, imported module) -> the lines of the importer where it is imported."""
    edges = defaultdict(list)
    for name, path in MODULES.items():
        for line, source, imported in _imports(name, path):
            target = f"{source}.{imported}" if imported and f"{source}.{imported}" in MODULES else source
            if target != name and target in MODULES:
                edges[(name, target)].append(line)
    return edges


def _import_graph() -> dict[str, set[str]]:
    graph = defaultdict(set)
    for importer, imported in _import_edges():
        graph[importer].add(imported)
    return graph


def _cycles(graph: dict[str, set[str]]) -> list[list[str]]:
    """The strongly connected components of more than one node (Tarjan), each sorted: every import cycle lies
    inside one of them."""
    index, low, stack, on_stack, cycles = {}, {}, [], set(), []
    nodes = sorted(set(graph) | {w for targets in graph.values() for w in targets})
    graph = defaultdict(set, graph)

    def visit(v):
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

    for v in nodes:
        if v not in index:
            visit(v)
    return sorted(cycles)


# The layers, lowest first (docs/architecture.md, "Layers"). A unit is a folder of afmid/ or a top-level module
# (``afmid`` itself: the package's ``__init__``). A unit may import units of its own layer or of lower layers,
# never a higher one; units of one layer must not import each other in a cycle (the folder-cycle test).
LAYERS: tuple[tuple[str, ...], ...] = (
    ("errors", "registry", "version", "threads", "tempfiles", "interrupts", "progress", "config_messages",
     "quantity_text"),
    ("terms",),
    ("kernels",),
    ("physics",),
    ("preprocess",),
    ("io",),
    ("config", "sections", "placeholders"),
    ("simulate",),
    ("fit",),
    ("runcheck", "runfile", "joint_runfile"),
    ("diagnosis",),
    ("batch", "maps"),
    ("report",),
    ("coverage",),
    ("api",),
    ("cli",),
    ("demo", "afmid"),
)
RANK = {unit: rank for rank, units in enumerate(LAYERS) for unit in units}

def unit_of(module: str) -> str:
    """The layer unit of a dotted module name: its folder under afmid/, or the top-level module's name."""
    parts = module.split(".")
    return parts[1] if len(parts) > 1 else parts[0]


def _upward_imports() -> dict[tuple[str, str], list[str]]:
    """(importing unit, imported unit) -> 'file:line imports module' for every import into a higher layer."""
    upward = defaultdict(list)
    for (importer, imported), lines in sorted(_import_edges().items()):
        low, high = unit_of(importer), unit_of(imported)
        if RANK[high] > RANK[low]:
            where = MODULES[importer].relative_to(PACKAGE.parent)
            upward[(low, high)] += [f"{where}:{line} imports {imported}" for line in sorted(set(lines))]
    return upward


def _folder_graph() -> dict[str, set[str]]:
    graph = defaultdict(set)
    for importer, imported in _import_edges():
        if unit_of(importer) != unit_of(imported):
            graph[unit_of(importer)].add(unit_of(imported))
    return graph


def layer_report() -> dict[str, list[str]]:
    """What the layer tests see, for a person breaking the cycles (``python -c`` over this module)."""
    return {"upward": [f"{pair}: {where}" for pair, where in _upward_imports().items()],
            "module cycles": [" ".join(c) for c in _cycles(_import_graph())],
            "folder cycles": [" ".join(c) for c in _cycles(_folder_graph())]}


def test_every_unit_has_a_layer():
    units = {unit_of(name) for name in MODULES}
    assert sorted(units - set(RANK)) == [], "add the unit to LAYERS here and to docs/architecture.md"
    assert sorted(set(RANK) - units) == [], "a unit in LAYERS that no longer exists"


def test_no_import_into_a_higher_layer():
    """Issue 30 removed the last ones: no exception is listed, none may come back."""
    assert _upward_imports() == {}, "imports into a higher layer (docs/architecture.md, Layers)"


def test_no_import_cycle_between_folders():
    assert _cycles(_folder_graph()) == [], "folder-level import cycles"


def test_the_layer_tests_see_lazy_and_type_checking_imports(tmp_path):
    """The reader counts an import inside a function and one under ``if TYPE_CHECKING:`` (a regression to the
    old reader, which dropped TYPE_CHECKING blocks, would make this fail)."""
    module = tmp_path / "probe.py"
    module.write_text("from typing import TYPE_CHECKING\nif TYPE_CHECKING:\n    from afmid.fit import forces\n"
                      "def f():\n    import afmid.report.fit_text\n    from afmid.io.trace import Trace\n")
    found = {(line, source, imported) for line, source, imported in _imports("afmid.probe", module)}
    assert found == {(3, "afmid.fit", "forces"), (5, "afmid.report.fit_text", None), (6, "afmid.io.trace", "Trace")}


def test_no_module_imports_a_module_that_imports_it_back():
    assert _cycles(_import_graph()) == [], "module-level import cycles (lazy and TYPE_CHECKING included)"


def test_the_cantilever_is_declared_once():
    """One lever type (issue 30): ``afmid.io.cantilever.Cantilever``; the stages' views of it have other names."""
    found = [f"{path.relative_to(PACKAGE.parent)}:{node.lineno}" for path in MODULES.values()
             for node in ast.walk(_tree(path)) if isinstance(node, ast.ClassDef) and node.name == "Cantilever"]
    assert found == ["afmid/io/cantilever.py:" + str(next(
        node.lineno for node in ast.walk(_tree(MODULES["afmid.io.cantilever"]))
        if isinstance(node, ast.ClassDef) and node.name == "Cantilever"))]


def test_no_module_imports_another_modules_private_names():
    offences = [f"{MODULES[name].relative_to(PACKAGE.parent)}:{line} imports {imported} from {source}"
                for name, path in MODULES.items() for line, source, imported in _imports(name, path)
                if imported and imported.startswith("_") and not imported.startswith("__") and source != name]
    assert offences == []


def _module_aliases(tree: ast.Module) -> dict[str, str]:
    """Local name -> afmid module it names, for every ``import afmid...`` and ``from afmid... import module``."""
    aliases = {}
    for node in ast.walk(tree):
        if isinstance(node, ast.Import):
            for alias in node.names:
                if alias.name.startswith("afmid"):
                    aliases[alias.asname or "afmid"] = alias.name if alias.asname else "afmid"
        elif isinstance(node, ast.ImportFrom) and not node.level and (node.module or "").startswith("afmid"):
            for alias in node.names:
                if f"{node.module}.{alias.name}" in MODULES:
                    aliases[alias.asname or alias.name] = f"{node.module}.{alias.name}"
    return aliases


def _private_reads(name: str, tree: ast.Module) -> list[tuple[int, str]]:
    """(line, ``module._name``) for every private attribute of another afmid module read in ``tree``."""
    aliases, found = _module_aliases(tree), []
    for node in ast.walk(tree):
        if isinstance(node, ast.Attribute) and node.attr.startswith("_") and not node.attr.startswith("__"):
            head, _, rest = ast.unparse(node.value).partition(".")
            module = aliases.get(head, "") + (f".{rest}" if rest and head in aliases else "")
            if module in MODULES and module != name:
                found.append((node.lineno, f"{module}.{node.attr}"))
    return found


def test_no_module_reads_another_modules_private_attributes():
    """``other_module._name`` is reaching into its privates as much as importing ``_name`` is (issue 30)."""
    offences = [f"{path.relative_to(PACKAGE.parent)}:{line} reads {what}"
                for name, path in MODULES.items() for line, what in _private_reads(name, _tree(path))]
    assert offences == []


def test_the_private_reads_check_sees_every_import_form():
    probe = ast.parse("import afmid.fit.pipeline\nimport afmid.fit.forces as f\nfrom afmid.fit import system\n"
                      "x = afmid.fit.pipeline._a + f._b + system._c + f.__doc__ + f.public\n")
    assert sorted(_private_reads("afmid.probe", probe)) == [
        (4, "afmid.fit.forces._b"), (4, "afmid.fit.pipeline._a"), (4, "afmid.fit.system._c")]


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


#: What dates a comment instead of explaining it: an issue number, a work session, the work log. The history of a
#: measurement belongs in docs/lab/ or the changelog; the code keeps the reason and the number.
HISTORY_REFERENCE = re.compile(r"[Ii]ssue[ -]?#?[0-9]+|[Ss]ession [0-9]+|[Ww]ork ?log")


def _history_references(text: str) -> list[int]:
    """The 1-based lines of ``text`` that cite an issue, a session or the work log."""
    return [number for number, line in enumerate(text.splitlines(), 1) if HISTORY_REFERENCE.search(line)]


#: The package's text files: its modules, and the templates it ships (numba's caches beside them are binary).
TEXT_SUFFIXES = {".py", ".yaml", ".yml", ".html", ".css", ".js", ".json", ".md", ".txt", ".toml"}


def test_no_comment_cites_an_issue_a_session_or_the_work_log():
    files = sorted(path for path in PACKAGE.rglob("*") if path.is_file() and path.suffix in TEXT_SUFFIXES)
    assert set(MODULES.values()) <= set(files)
    offences = [f"{path.relative_to(PACKAGE.parent)}:{line}" for path in files
                for line in _history_references(path.read_text())]
    assert offences == []


def test_the_history_check_sees_every_form():
    text = "ok\n# measured (issue 13)\n# see issue #28\n# the issue-14 machine\n# session 11\n# work log\n# Worklog\n"
    assert _history_references(text) == [2, 3, 4, 5, 6, 7]
    assert _history_references("# the issue is the lever\n# a sessions file\n") == []
