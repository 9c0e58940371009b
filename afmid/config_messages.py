"""A pydantic validation error as the one line afmid promises: the file, the key, what was expected.

``validation_error`` turns the first error (others appended, at most two) into a :class:`afmid.errors.ConfigError`:
an unknown key with the closest allowed one and the section's allowed keys, a bound as the user wrote it, a
value matching no member of a union merged into "expected a or b", and a section validator's own
"section.key: message" kept with its key.
"""

from __future__ import annotations

import math
import re
from pathlib import Path
from typing import Any

from pydantic import BaseModel, ValidationError

from afmid.errors import ConfigError
from afmid.registry import closest


def format_value(value: Any) -> str:
    """A value as quoted in a message: repr, a long mapping or list cut at 60 characters."""
    if isinstance(value, float):
        return repr(value) if math.isfinite(value) else str(value)
    if isinstance(value, (dict, list)):
        text = repr(value)
        return text if len(text) < 60 else text[:57] + "..."
    return repr(value)


def _format_limit(limit: Any) -> str:
    """A bound as the user wrote it: 0 rather than 0.0, 1e-07 and 1e+09 as is."""
    if isinstance(limit, float) and limit.is_integer() and abs(limit) < 1e6:
        return str(int(limit))
    if isinstance(limit, float):
        return f"{limit:g}"
    return format_value(limit)


def _type_arguments(annotation) -> list:
    """The types inside an optional or a list annotation (``X | None``, ``list[X]``), one level deep."""
    import typing

    return [a for a in typing.get_args(annotation) if a is not type(None)]


def _section_fields(model: type[BaseModel], loc: tuple) -> list[str]:
    """The allowed keys at ``loc`` (the parent of an unknown key)."""
    current: Any = model
    for part in loc:
        if isinstance(part, int):  # an item of a list section: same model
            continue
        field = getattr(current, "model_fields", {}).get(part)
        if field is None:
            return []
        models = [a for a in (field.annotation, *_type_arguments(field.annotation))
                  if isinstance(a, type) and issubclass(a, BaseModel)]
        if not models:
            return []
        current = models[0]
    return list(getattr(current, "model_fields", {}))


def _describe(error: dict, schema: type[BaseModel]) -> tuple[str, str]:
    """Key path and a human message for one pydantic error."""
    loc = tuple(p for p in error["loc"] if not (isinstance(p, str) and p.startswith("function-")))
    # pydantic appends the union member type to the loc of union errors; keep the field path only
    loc = tuple(p for p in loc if not (isinstance(p, str) and p in {"str", "int", "float", "bool", "constrained-float"}))
    key = ".".join(str(p) for p in loc)
    kind = error["type"]
    ctx = error.get("ctx") or {}
    value = error.get("input")
    if kind == "extra_forbidden":
        allowed = _section_fields(schema, loc[:-1])
        hint = closest(str(loc[-1]), allowed)
        msg = "unknown key"
        if hint:
            msg += f" (did you mean {hint!r}?)"
        return key, msg + (f"; allowed keys: {', '.join(allowed)}" if allowed else "")
    if kind == "missing":
        return key, "required key is missing"
    bounds = {"greater_than": ">", "greater_than_equal": ">=", "less_than": "<", "less_than_equal": "<="}
    if kind in bounds:
        limit = next(iter(ctx.values()))
        return key, f"must be {bounds[kind]} {_format_limit(limit)}, got {format_value(value)}"
    if kind == "finite_number":
        return key, f"must be a finite number, got {format_value(value)}"
    if kind in {"float_parsing", "float_type", "int_parsing", "int_type", "int_from_float"}:
        expected = "a whole number" if kind.startswith("int") else "a number"
        return key, f"expected {expected}, got {format_value(value)}"
    if kind == "string_type":
        return key, f"expected a string, got {format_value(value)}"
    if kind in {"bool_parsing", "bool_type"}:
        return key, f"expected true or false, got {format_value(value)}"
    if kind == "path_type":
        return key, f"expected a file path, got {format_value(value)}"
    if kind == "literal_error":
        return key, f"must be one of {ctx.get('expected')}, got {format_value(value)}"
    if kind in {"model_type", "dict_type"}:
        return key, f"expected a mapping of keys, got {format_value(value)}"
    if kind == "list_type":
        return key, f"expected a list, got {format_value(value)}"
    if kind == "value_error":
        text = str(ctx.get("error", error["msg"]))
        # A section's own validator names the key it is about: "section.key: message".
        named = _NAMED_KEY.match(text)
        if named and (not key or named["key"].startswith(f"{key}.")):
            return named["key"], named["message"]
        return key, text
    return key, f"{error['msg']}, got {format_value(value)}"


_NAMED_KEY = re.compile(r"^(?P<key>[A-Za-z_][\w.\[\]]*): (?P<message>.+)$")
_EXPECTED = re.compile(r"^expected (?P<what>.+), got (?P<got>.+)$")


def _merge_alternatives(described: list[tuple[str, str]]) -> list[tuple[str, str]]:
    """One message per key for a value matching no member of a union (``str | int``): 'expected a or b, got v'."""
    merged: list[tuple[str, str]] = []
    for key, msg in described:
        if merged and merged[-1][0] == key:
            this, last = _EXPECTED.match(msg), _EXPECTED.match(merged[-1][1])
            if this and last and this["got"] == last["got"]:
                merged[-1] = (key, f"expected {last['what']} or {this['what']}, got {this['got']}")
                continue
        merged.append((key, msg))
    return merged


def validation_error(exc: ValidationError, file: str | Path | None, schema: type[BaseModel]) -> ConfigError:
    """Convert the first pydantic error into a one-line :class:`ConfigError` (others appended)."""
    described = _merge_alternatives([_describe(e, schema) for e in exc.errors()])
    key, msg = described[0]
    if len(described) > 1:
        msg += f" (and {len(described) - 1} more: " + "; ".join(f"{k}: {m}" for k, m in described[1:3]) + ")"
    return ConfigError(msg, file=file, key=key or None)
