"""``mi-shadowgs report RUN``: (re)write ``RUN/report.html`` from ``RUN/summary.json`` (its
speed-against-error section first brought up to date with ``RUN/speed_error/``).

Only into a folder that ``mi-shadowgs run`` wrote (its manifest lists ``report.html``).
"""

from __future__ import annotations

import argparse


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("run", help="run folder written by `mi-shadowgs run`")


def run(args) -> int:
    from mi_shadowgs.io.provenance import MANIFEST_NAME, ProvenanceError, read_manifest
    from mi_shadowgs.io.report import write_report

    manifest = read_manifest(args.run)
    if (manifest is None or manifest.get("command") != "run"
            or "report.html" not in manifest["files"]):
        raise ProvenanceError(f"{args.run}: not a run folder of `mi-shadowgs run` (no "
                              f"{MANIFEST_NAME} listing report.html); the report is written "
                              "only there")
    from pathlib import Path

    from mi_shadowgs.stages.common import check_run_stages
    from mi_shadowgs.summary import refresh_speed_error

    check_run_stages(args.run)  # a summary of stages made from another stage's files
    refresh_speed_error(Path(args.run))  # plots that validation.speed_error added since
    page = write_report(args.run)
    print(f"wrote {page}")
    return 0
