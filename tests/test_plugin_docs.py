"""One parameter table per plugin: ``docs/plugins.md`` is generated from the plugins'
docstrings (``python -m mi_shadowgs.plugins._docs > docs/plugins.md``), and every Mitsuba
property a plugin reads has a row there."""

from __future__ import annotations

import re
from pathlib import Path

import pytest

from mi_shadowgs.plugins import _docs as plugin_docs

ROOT = Path(__file__).resolve().parents[1]
# props.get("name"...), "name" in props, _bool(props, "name"...)
PROPERTY_READ = re.compile(r'props\.get\("(\w+)"|"(\w+)" in props|_bool\(props, "(\w+)"')


def test_committed_docs_equal_generated():
    committed = (ROOT / "docs" / "plugins.md").read_text(encoding="utf-8")
    assert committed == plugin_docs.plugins_markdown(), (
        "docs/plugins.md differs from the plugins' docstrings: run "
        "python -m mi_shadowgs.plugins._docs > docs/plugins.md")


def test_every_plugin_module_is_documented():
    modules = {p.stem for p in (ROOT / "mi_shadowgs" / "plugins").glob("*.py")
               if not p.stem.startswith("_")}
    assert modules == set(plugin_docs.PLUGINS)


@pytest.mark.parametrize("name", plugin_docs.PLUGINS)
def test_every_property_read_has_a_row(name):
    source = (ROOT / "mi_shadowgs" / "plugins" / f"{name}.py").read_text(encoding="utf-8")
    read = {next(g for g in m.groups() if g) for m in PROPERTY_READ.finditer(source)}
    tuple_props = re.search(r"_CONFIG_PROPS = \(([^)]*)\)", source)
    if tuple_props:  # read in a loop: props.get(k) for k in _CONFIG_PROPS
        read |= set(re.findall(r'"(\w+)"', tuple_props.group(1)))
    assert "filename" in read  # the scan finds what every plugin reads
    documented = {n for row in plugin_docs.parameter_rows(plugin_docs.plugin_docstring(name))
                  for n in re.findall(r"`([\w.<>]+)`", row[0])}
    assert read - documented == set(), f"{name}: properties without a row"


def test_generator_refuses_a_docstring_without_parameters():
    with pytest.raises(ValueError, match="lists no parameter"):
        plugin_docs.section("## `x` (integrator)\n\nNo list here.\n")
    with pytest.raises(ValueError, match="name | type"):
        plugin_docs.section("## `x`\n\n- `a` | string | only three\n")


def test_generator_makes_a_table_with_continued_descriptions():
    doc = ("## `x` (integrator)\n\nText.\n\n- `a` | float | `1` | | First line\n"
           "  goes on.\n- `b` | Float [N] | from file | differentiable | B.\n\nAfter.\n")
    assert plugin_docs.section(doc) == (
        "## `x` (integrator)\n\nText.\n\n| Parameter | Type | Default | Flags | Description |\n"
        "|---|---|---|---|---|\n| `a` | float | `1` | | First line goes on. |\n"
        "| `b` | Float [N] | from file | differentiable | B. |\n\nAfter.\n")
