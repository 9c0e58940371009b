"""Template placeholders: a value `afmid init-config` wrote as an example must not run a fit unnoticed.

The template's cantilever values (k = 40 N/m, f0 = 300 kHz, Q = 150, R = 10 nm) are examples, not anyone's
calibration. Each carries the mark :data:`MARK` in its line's comment. A YAML loader drops comments, so the
check reads the config's raw text: a key whose line (not commented out) carries the mark AND whose value, after
``--set``, is still the template's value is a placeholder, and ``afmid fit`` stops with one line naming the
file, the key and what to do (exit 2). Editing the value, or deleting the mark (the value is right after
all: a lever that does have Q = 150), lets the fit run. Only ``section.key`` lines are marked (the template's
depth); an afmid trace file's calibration, copied by ``init-config --from``, replaces the comment and so the mark.
"""

from __future__ import annotations

import re
from pathlib import Path

from afmid.errors import ConfigError

#: The mark on a template value's line (in its comment).
MARK = "CHECK: template example"

_SECTION = re.compile(r"^(?P<section>[A-Za-z_]\w*):")
_MARKED = re.compile(r"^  (?P<key>[A-Za-z_]\w*):[^#]*#.*" + re.escape(MARK))


def marked_keys(text: str) -> list[str]:
    """``section.key`` of every line of config ``text`` that carries :data:`MARK` (commented-out lines aside)."""
    keys, section = [], None
    for line in text.splitlines():
        if (m := _SECTION.match(line)) is not None:
            section = m["section"]
        elif section is not None and (m := _MARKED.match(line)) is not None:
            keys.append(f"{section}.{m['key']}")
    return keys


def _value(tree, dotted: str):
    for part in dotted.split("."):
        tree = tree.get(part) if isinstance(tree, dict) else getattr(tree, part, None)
    return tree


def placeholders(path: str | Path, config) -> list[str]:
    """The keys of the config file ``path`` (loaded as ``config``, overrides applied) that still hold a marked
    template value."""
    import yaml

    from afmid.config import template_text

    template = yaml.safe_load(template_text())
    text = Path(path).read_text(encoding="utf-8", errors="replace")
    return [key for key in marked_keys(text)
            if _value(template, key) is not None and _value(config, key) == _value(template, key)]


def refuse_placeholders(path: str | Path, config) -> None:
    """Raise a one-line ConfigError (exit 2) naming the first placeholder left in ``path``, if any."""
    left = placeholders(path, config)
    if not left:
        return
    more = f" (also {', '.join(left[1:])})" if len(left) > 1 else ""
    raise ConfigError(f"{_value(config, left[0])} is the template's example, not a calibration ('{MARK}' on its "
                      f"line){more}: put your measured value, or delete the mark if this value is right",
                      file=path, key=left[0])
