"""A small, checked registry used for every pluggable part of afmid.

Force models, physical effects, library terms, differentiators and file readers
are each declared once, with metadata (name, formula, units, valid range,
references). Declarations are validated when registered, so a malformed one
fails at import time in the tests rather than in a user's run.
"""

from __future__ import annotations

import difflib
from collections.abc import Callable, Iterator
from typing import Generic, TypeVar

from afmid.errors import DefinitionError

T = TypeVar("T")


def closest(name: str, choices: list[str]) -> str | None:
    """The choice most similar to ``name`` (for 'did you mean' hints), or None."""
    hits = difflib.get_close_matches(name, choices, n=1, cutoff=0.5)
    return hits[0] if hits else None


def unknown_name_message(kind: str, name: str, choices: list[str]) -> str:
    """A one-line message for an unknown registry name, suggesting the closest one."""
    hint = closest(name, choices)
    allowed = ", ".join(sorted(choices))
    msg = f"unknown {kind} {name!r}"
    if hint:
        msg += f" (did you mean {hint!r}?)"
    return msg + f"; allowed: {allowed}"


class Registry(Generic[T]):
    """Name -> declaration mapping with a validation hook run on registration."""

    def __init__(self, kind: str, validate: Callable[[T], None] | None = None):
        self.kind = kind
        self._items: dict[str, T] = {}
        self._validate = validate

    def register(self, item: T) -> T:
        name = getattr(item, "name", None)
        if not isinstance(name, str) or not name.isidentifier():
            raise DefinitionError(f"{self.kind}: name must be an identifier, got {name!r}")
        if name in self._items:
            raise DefinitionError(f"{self.kind} {name!r} is registered twice")
        for field in ("title", "references"):
            if not getattr(item, field, None):
                raise DefinitionError(f"{self.kind} {name!r}: missing {field}")
        if self._validate is not None:
            try:
                self._validate(item)
            except DefinitionError:
                raise
            except Exception as exc:  # surface any check failure as a definition error
                raise DefinitionError(f"{self.kind} {name!r}: {exc}") from exc
        self._items[name] = item
        return item

    def get(self, name: str) -> T:
        """Look up ``name``; raises KeyError with a 'did you mean' message."""
        try:
            return self._items[name]
        except KeyError:
            raise KeyError(unknown_name_message(self.kind, name, list(self._items))) from None

    def names(self) -> list[str]:
        return list(self._items)

    def __contains__(self, name: object) -> bool:
        return name in self._items

    def __iter__(self) -> Iterator[T]:
        return iter(self._items.values())

    def __len__(self) -> int:
        return len(self._items)
