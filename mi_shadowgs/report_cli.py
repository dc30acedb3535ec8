"""``mi-shadowgs report RUN``: (re)write ``RUN/report.html`` from ``RUN/summary.json``."""

from __future__ import annotations

import argparse


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("run", help="run folder written by `mi-shadowgs run`")


def run(args) -> int:
    from .report import write_report

    page = write_report(args.run)
    print(f"wrote {page}")
    return 0
