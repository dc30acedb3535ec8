"""``docs/plugins.md`` from the plugins' own docstrings: each plugin is documented once.

    python -m mi_shadowgs.plugins._docs > docs/plugins.md

A plugin module's docstring is its Markdown section; its parameters are a list whose items
read ``- `name` | type | default | flags | description`` (the description may go on over
indented lines), written out as one table. ``tests/test_plugin_docs.py`` checks that the
committed ``docs/plugins.md`` is this text. Reads the source files (``ast``): no Mitsuba.
The leading underscore keeps ``plugins.register`` from importing it as a plugin.
"""

from __future__ import annotations

import ast
from pathlib import Path

# In the order of docs/plugins.md.
PLUGINS = ("surfel_raster", "surfel_relight")

HEADER = """# Mitsuba plugins

<!-- Generated from the plugins' docstrings (mi_shadowgs/plugins/*.py); do not edit:
     python -m mi_shadowgs.plugins._docs > docs/plugins.md -->

Importing `mi_shadowgs` selects the variant (`llvm_ad_rgb` by default);
`mi_shadowgs.register_plugins()` registers every plugin in `mi_shadowgs.plugins` for it, and
after a later `mi_shadowgs.set_variant(...)` they are registered again for the new variant.
"""

TABLE_HEAD = ("| Parameter | Type | Default | Flags | Description |",
              "|---|---|---|---|---|")
ROW_START = "- `"


def plugin_docstring(name: str) -> str:
    """The docstring of ``mi_shadowgs/plugins/<name>.py``."""
    path = Path(__file__).with_name(f"{name}.py")
    doc = ast.get_docstring(ast.parse(path.read_text(encoding="utf-8")))
    if not doc:
        raise ValueError(f"{path}: the plugin has no docstring")
    return doc


def parameter_rows(doc: str) -> list[list[str]]:
    """The parameter list of a plugin docstring as table rows of five cells."""
    return [_cells(item) for item in _items(doc.splitlines())[1]]


def _items(lines: list[str]) -> tuple[int, list[str], int]:
    """(first line, items joined into one line each, line after) of the parameter list."""
    start = next((i for i, line in enumerate(lines) if line.startswith(ROW_START)), None)
    if start is None:
        return len(lines), [], len(lines)
    items, i = [], start
    while i < len(lines) and (lines[i].startswith(ROW_START) or
                              (lines[i].startswith("  ") and items)):
        if lines[i].startswith(ROW_START):
            items.append(lines[i][2:])
        else:
            items[-1] += " " + lines[i].strip()
        i += 1
    return start, items, i


def _cells(item: str) -> list[str]:
    cells = [c.strip() for c in item.split("|", 4)]
    if len(cells) != 5:
        raise ValueError(f"plugin parameter {item[:40]!r}...: needs 'name | type | default | "
                         "flags | description'")
    return cells


def section(doc: str) -> str:
    """A plugin docstring as Markdown: its parameter list becomes a table."""
    lines = doc.splitlines()
    start, items, end = _items(lines)
    if not items:
        raise ValueError(f"{lines[0]}: the docstring lists no parameter "
                         f"('{ROW_START}name` | type | default | flags | description')")
    table = [*TABLE_HEAD, *("|" + "|".join(f" {c} " if c else " " for c in _cells(item)) + "|"
                            for item in items)]
    return "\n".join([*lines[:start], *table, *lines[end:]]).rstrip() + "\n"


def plugins_markdown() -> str:
    """The whole of ``docs/plugins.md``."""
    return "\n".join([HEADER, *(section(plugin_docstring(n)) for n in PLUGINS)])


if __name__ == "__main__":
    print(plugins_markdown(), end="")
