"""docs/cli.md is generated from the command line's parsers (``python -m scripts.cli_docs``):
the committed page is current, and every command and option has its place on it."""

from __future__ import annotations

import argparse
from pathlib import Path

from mi_shadowgs.cli import COMMANDS, build_parser
from scripts import cli_docs

ROOT = Path(__file__).resolve().parents[1]


def test_committed_cli_page_equals_generated():
    committed = (ROOT / "docs" / "cli.md").read_text(encoding="utf-8")
    assert committed == cli_docs.cli_markdown(), (
        "docs/cli.md differs from the CLI's parsers: run python -m scripts.cli_docs")


def test_every_command_and_option_is_on_the_page():
    page = cli_docs.cli_markdown()
    sub = next(a for a in build_parser()._actions
               if isinstance(a, argparse._SubParsersAction))
    for name in COMMANDS:
        assert f"\n## {name}\n" in page
        for action in sub.choices[name]._actions:
            for option in action.option_strings:
                if option not in ("-h", "--help"):
                    assert f"`{option}`" in page, (name, option)


def test_the_page_does_not_depend_on_the_terminal_width(monkeypatch):
    monkeypatch.setenv("COLUMNS", "40")
    narrow = cli_docs.cli_markdown()
    monkeypatch.setenv("COLUMNS", "240")
    assert cli_docs.cli_markdown() == narrow
