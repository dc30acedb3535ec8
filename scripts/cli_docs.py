"""docs/cli.md from the ``mi-shadowgs`` argparse parsers (``make docs`` runs it).

The page lists every command with its description, its positional arguments and its options
(flags, value, default, help), read from ``mi_shadowgs.cli.build_parser()``. The output
depends on the parsers alone, so ``tests/test_cli_docs.py`` checks that the committed page
is current::

    python -m scripts.cli_docs [--out docs/cli.md] [--check]
"""

from __future__ import annotations

import argparse
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
HEADER = """# Command line

Every command of `mi-shadowgs`, with its arguments and options. This page is generated from
the command line's own parsers (`python -m scripts.cli_docs`); `mi-shadowgs COMMAND --help`
prints the same.
"""


def _cell(text: str) -> str:
    return " ".join(str(text).split()).replace("|", "\\|")


def _value(action: argparse.Action) -> str:
    if action.nargs == 0:
        return ""
    if action.choices is not None:
        return "{" + ",".join(str(c) for c in action.choices) + "}"
    metavar = action.metavar or action.dest.upper()
    return metavar if isinstance(metavar, str) else " ".join(metavar)


def _default(action: argparse.Action) -> str:
    default = action.default
    if action.nargs == 0 or default is None or default is argparse.SUPPRESS:
        return ""
    if isinstance(default, (list, tuple)):
        default = " ".join(str(d) for d in default)
    return f"`{default}`" if str(default) != "" else ""


def actions_table(parser: argparse.ArgumentParser, positional: bool) -> list[str]:
    rows = []
    for action in parser._actions:  # argparse has no public list of a parser's arguments
        if isinstance(action, (argparse._HelpAction, argparse._SubParsersAction)):
            continue
        if bool(action.option_strings) == positional or action.help == argparse.SUPPRESS:
            continue
        if positional:
            name = f"`{action.metavar or action.dest}`"
        else:
            name = ", ".join(f"`{o}`" for o in action.option_strings)
        value = _value(action)
        rows.append(f"| {name} | {_cell(value) if value else ''} | {_default(action)} | "
                    f"{_cell(action.help or '')} |")
    if not rows:
        return []
    title = "Arguments" if positional else "Options"
    return [f"**{title}**", "", "| name | value | default | description |", "|---|---|---|---|",
            *rows, ""]


def cli_markdown() -> str:
    from mi_shadowgs.cli import COMMANDS, build_parser

    parser = build_parser()
    sub = next(a for a in parser._actions if isinstance(a, argparse._SubParsersAction))
    lines = [HEADER, "## `mi-shadowgs`", "", _cell(parser.description or ""), "",
             *actions_table(parser, positional=False)]
    lines += ["| command | what it does |", "|---|---|"]
    lines += [f"| [`{name}`](#{name}) | {_cell(help_text)} |"
              for name, (_, help_text) in COMMANDS.items()]
    lines.append("")
    for name, (_, help_text) in COMMANDS.items():
        p = sub.choices[name]
        usage = " ".join(p.format_usage().split())
        lines += [f"## {name}", "", _cell(help_text), "", "```text", usage, "```", ""]
        lines += actions_table(p, positional=True)
        lines += actions_table(p, positional=False)
    return "\n".join(lines).rstrip("\n") + "\n"


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description="Write docs/cli.md from the CLI's parsers.")
    ap.add_argument("--out", default=str(ROOT / "docs" / "cli.md"))
    ap.add_argument("--check", action="store_true",
                    help="write nothing; exit 1 when the page differs from the parsers")
    args = ap.parse_args(argv)
    text = cli_markdown()
    out = Path(args.out)
    if args.check:
        if not out.is_file() or out.read_text(encoding="utf-8") != text:
            print(f"{out} is not current: run python -m scripts.cli_docs", file=sys.stderr)
            return 1
        return 0
    out.write_text(text, encoding="utf-8")
    print(f"wrote {out}")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
