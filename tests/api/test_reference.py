"""docs/python.md's Reference is the front door's API as the code declares it.

Every name of ``afmid.__all__`` has a heading there, every public method and property of the front door's classes a
member line, and every documented name exists with the documented signature: argument names in order, their kinds
(``*`` keyword-only, ``*args``, ``**kwargs``), their defaults, and the return type where the code declares one. A
changed signature, a new public method or a name dropped from the package fails here until the page says so.
"""

from __future__ import annotations

import ast
import dataclasses
import inspect
import re
import textwrap
from pathlib import Path

import pytest

import afmid

DOC = Path(__file__).resolve().parents[2] / "docs" / "python.md"

#: A heading of the Reference: ### `afmid.NAME[.ATTR](ARGS) -> RETURN` (the arguments and return optional).
HEADING = re.compile(r"^### `afmid\.(?P<name>[\w.]+)(?:\((?P<args>.*)\))?(?: -> (?P<returns>[^`]+))?`\s*$")
#: One documented member at the head of a bullet: `.name(ARGS) -> RETURN` or `Class.name(ARGS) -> RETURN`.
MEMBER = re.compile(r"`(?P<owner>[A-Z]\w*)?\.(?P<name>\w+)(?:\((?P<args>[^`]*)\))?(?: -> (?P<returns>[^`]+))?`")
#: The head of a member bullet: code spans joined by ", " up to the first ":" after a span.
BULLET_HEAD = re.compile(r"^- ((?:`[^`]+`(?:, )?)+)")

#: Public members that are the pipeline's, not the front door's (named so that a new one is a decision).
NOT_FRONT_DOOR = {
    "Trace": {"drive_for": "the drive columns the fit stage builds for a detrend setting",
              # dataclass fields the loaders fill for the pipeline and the run file
              "sources": "", "overridden": "", "drive": "", "first_sample": "", "reading": "", "time": ""},
    "Parameters": {"COLUMNS": "the column names of to_dicts, listed in its line"},
}


def reference_text(text: str) -> tuple[str, int]:
    """The Reference section of the page (from its heading to the next level-2 heading) and the number of the
    page's line before it."""
    start = text.index("\n## Reference\n")
    end = text.find("\n## ", start + 1)
    return text[start:end if end >= 0 else len(text)], text[:start].count("\n")


def documented(text: str) -> list[dict]:
    """Each heading with the member lines under it: {name, args, returns, line, members: [...]}."""
    entries: list[dict] = []
    section, offset = reference_text(text)
    for number, line in enumerate(section.splitlines(), offset + 1):
        match = HEADING.match(line)
        if match:
            entries.append({**match.groupdict(), "line": number, "members": []})
            continue
        head = BULLET_HEAD.match(line)
        if head and entries:
            for member in MEMBER.finditer(head.group(1)):
                entries[-1]["members"].append({**member.groupdict(), "line": number})
    return entries


def _resolve(dotted: str):
    obj = afmid
    for part in dotted.split("."):
        obj = getattr(obj, part)
    return obj


def _documented_parameters(args: str) -> list[tuple[str, str, str | None]]:
    """(name, kind, default source) of the documented argument list, read with Python's own parser."""
    tree = ast.parse(f"def f({args}): pass").body[0].args
    out = [(a.arg, "POSITIONAL_OR_KEYWORD", None) for a in tree.posonlyargs + tree.args]
    for i, default in enumerate(tree.defaults, len(out) - len(tree.defaults)):
        out[i] = (out[i][0], out[i][1], ast.unparse(default))
    if tree.vararg:
        out.append((tree.vararg.arg, "VAR_POSITIONAL", None))
    for a, default in zip(tree.kwonlyargs, tree.kw_defaults):
        out.append((a.arg, "KEYWORD_ONLY", None if default is None else ast.unparse(default)))
    if tree.kwarg:
        out.append((tree.kwarg.arg, "VAR_KEYWORD", None))
    return out


def _actual_default(obj, parameter: inspect.Parameter):
    """The parameter's default; a dataclass field's default factory called (the signature shows ``<factory>``)."""
    if dataclasses.is_dataclass(obj) and inspect.isclass(obj):
        field = {f.name: f for f in dataclasses.fields(obj)}.get(parameter.name)
        if field is not None and field.default_factory is not dataclasses.MISSING:
            return field.default_factory()
    return parameter.default


def _same_default(source: str, actual) -> bool:
    """The documented default equals the code's: by value where it is a literal, else by its repr (nan)."""
    try:
        return repr(ast.literal_eval(source)) == repr(actual)
    except ValueError:
        return source.replace('"', "'") == repr(actual)


def _type_name(annotation) -> str:
    """A type as the page writes it: no quotes, no module prefix, no generic arguments ('np.ndarray' -> 'ndarray')."""
    text = annotation if isinstance(annotation, str) else getattr(annotation, "__name__", str(annotation))
    text = re.sub(r"\[.*\]", "", text.replace("'", "").replace('"', "").replace(" ", ""))
    return re.sub(r"\b\w+\.(?=\w)", "", text)


def signature_problems(where: str, obj, args: str | None, returns: str | None, *, bound: bool) -> list[str]:
    """How the documented signature differs from the code's (empty when they agree)."""
    problems = []
    if args is not None:
        code = list(inspect.signature(obj).parameters.values())
        if bound and code and code[0].name in ("self", "cls"):
            code = code[1:]
        doc = _documented_parameters(args)
        code_shape = [(p.name, p.kind.name) for p in code]
        doc_shape = [(name, kind) for name, kind, _ in doc]
        if code_shape != doc_shape:
            problems.append(f"{where}: arguments {doc_shape} documented, the code has {code_shape}")
        else:
            for (name, _, source), parameter in zip(doc, code):
                has_default = parameter.default is not inspect.Parameter.empty
                if (source is None) == has_default:
                    problems.append(f"{where}: {name} {'has no' if has_default else 'has a'} default on the page")
                elif source is not None and not _same_default(source, _actual_default(obj, parameter)):
                    problems.append(f"{where}: {name}={source} documented, the code's default is "
                                    f"{_actual_default(obj, parameter)!r}")
    if returns is not None:
        target = obj.fget if isinstance(obj, property) else obj
        annotation = inspect.signature(target).return_annotation if callable(target) else inspect.Parameter.empty
        if annotation is not inspect.Parameter.empty and _type_name(annotation) != _type_name(returns):
            problems.append(f"{where}: returns {returns} documented, the code declares {annotation}")
    return problems


def _instance_attributes(owner) -> set[str]:
    """The names its ``__init__`` assigns as ``self.NAME = ...`` (attributes no class dictionary holds)."""
    init = vars(owner).get("__init__")
    if init is None or dataclasses.is_dataclass(owner):
        return set()
    tree = ast.parse(textwrap.dedent(inspect.getsource(init)))
    return {target.attr for node in ast.walk(tree) if isinstance(node, (ast.Assign, ast.AnnAssign))
            for target in (node.targets if isinstance(node, ast.Assign) else [node.target])
            if isinstance(target, ast.Attribute) and isinstance(target.value, ast.Name) and target.value.id == "self"}


def _member(owner, name: str):
    """The member as the class holds it (a property object, a classmethod's function, a field; None for an
    attribute its ``__init__`` sets)."""
    if name in _instance_attributes(owner) and not name.startswith("_"):
        return None, True
    for klass in inspect.getmro(owner):
        if name in vars(klass):
            raw = vars(klass)[name]
            if isinstance(raw, (classmethod, staticmethod)):
                return getattr(owner, name), False
            return raw, True
    if dataclasses.is_dataclass(owner) and name in {f.name for f in dataclasses.fields(owner)}:
        return dataclasses.fields(owner)[[f.name for f in dataclasses.fields(owner)].index(name)], True
    raise AttributeError(name)


def _field_problems(where: str, field: dataclasses.Field, returns: str | None) -> list[str]:
    if returns is not None and _type_name(field.type) != _type_name(returns):
        return [f"{where}: type {returns} documented, the field is {field.type}"]
    return []


def reference_problems(text: str) -> list[str]:
    """Everything the page documents that the code does not have as documented, and what it leaves out."""
    problems = []
    entries = documented(text)
    headed = {entry["name"] for entry in entries}
    problems += [f"afmid.{name} has no heading in the Reference" for name in afmid.__all__ if name not in headed]
    members_of: dict[str, set[str]] = {}
    for entry in entries:
        owner_name, _, attribute = entry["name"].partition(".")
        if attribute:  # a heading of a member (Trace.from_array) documents it
            members_of.setdefault(owner_name, set()).add(attribute)
        elif entry["args"]:  # a constructor's arguments document the fields they set
            arguments = _documented_parameters(entry["args"])
            members_of.setdefault(owner_name, set()).update(name for name, _, _ in arguments)
        where = f"docs/python.md:{entry['line']}: afmid.{entry['name']}"
        try:
            obj = _resolve(entry["name"])
        except AttributeError:
            problems.append(f"{where} does not exist")
            continue
        if callable(obj) and (entry["args"] is not None or entry["returns"] is not None):
            problems += signature_problems(where, obj, entry["args"], entry["returns"], bound=inspect.ismethod(obj))
        owner = obj if inspect.isclass(obj) else None
        for member in entry["members"]:
            mwhere = f"docs/python.md:{member['line']}: {entry['name']}.{member['name']}"
            if owner is None or (member["owner"] and member["owner"] != owner.__name__):
                problems.append(f"{mwhere}: a member line under a heading that is not its class")
                continue
            try:
                raw, bound = _member(owner, member["name"])
            except AttributeError:
                problems.append(f"{mwhere} does not exist")
                continue
            members_of.setdefault(owner.__name__, set()).add(member["name"])
            if isinstance(raw, dataclasses.Field):
                problems += _field_problems(mwhere, raw, member["returns"])
            elif isinstance(raw, property) or callable(raw):
                problems += signature_problems(mwhere, raw, None if isinstance(raw, property) else member["args"],
                                               member["returns"], bound=bound)
    for name in afmid.__all__:
        obj = getattr(afmid, name)
        if not inspect.isclass(obj):
            continue
        public = {m for klass in inspect.getmro(obj) if klass.__module__.startswith("afmid")
                  for m in vars(klass) if not m.startswith("_")}
        if dataclasses.is_dataclass(obj):
            public |= {f.name for f in dataclasses.fields(obj)}
        public |= {m for m in _instance_attributes(obj) if not m.startswith("_")}
        missing = public - members_of.get(name, set()) - set(NOT_FRONT_DOOR.get(name, {}))
        problems += [f"afmid.{name}.{m} is public but has no member line in the Reference" for m in sorted(missing)]
    return problems


def test_the_reference_documents_the_front_door_as_the_code_declares_it():
    assert reference_problems(DOC.read_text()) == []


def test_the_reference_lists_every_name_of_the_package():
    headed = {entry["name"] for entry in documented(DOC.read_text())}
    assert set(afmid.__all__) <= headed


@pytest.mark.parametrize("change, drifted, named", [
    # a documented argument the code does not have
    ("### `afmid.load(path, trace=None) -> Fit`", "### `afmid.load(path, trace=None, strict=True) -> Fit`",
     "afmid.load: arguments"),
    # a wrong default
    ("### `afmid.simulate_trace(config, progress=False) -> Trace`",
     "### `afmid.simulate_trace(config, progress=True) -> Trace`", "progress=True documented"),
    # keyword-only marker dropped
    ("- `.fit(trace, *, progress=False, name=None, separations=None) -> Fit`",
     "- `.fit(trace, progress=False, name=None, separations=None) -> Fit`", "ForceModel.fit: arguments"),
    # a wrong declared return type
    ("- `.force_curve() -> ForceCurve`", "- `.force_curve() -> Parameters`", "returns Parameters documented"),
    # a member that does not exist
    ("- `.names() -> list`", "- `.row_names() -> list`", "Parameters.row_names does not exist"),
    # a front-door name without a heading
    ("### `afmid.HigherMode(resonance_frequency, quality_factor, spring_constant)`", "### HigherMode",
     "afmid.HigherMode has no heading"),
    # a public method without a member line
    ("- `.to_pandas()`:", "- to_pandas:", "afmid.Parameters.to_pandas is public"),
    # a dataclass field with the wrong type
    ("- `.periods -> int`", "- `.periods -> float`", "ForceCurve.periods: type float"),
])
def test_the_check_sees_a_page_that_drifted_from_the_code(change, drifted, named):
    text = DOC.read_text()
    assert text.count(change) == 1, change
    problems = reference_problems(text.replace(change, drifted))
    assert any(named in problem for problem in problems), problems
