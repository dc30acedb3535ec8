"""A batch's results at a glance: ``batch.csv`` and ``batch.html`` in the batch folder.

One row per item, in the spec's order: its status (``finished``, ``reused``: every stage
made by an earlier call, ``failed``, ``pending``: not ended yet), its seconds in this call,
the most memory one of its commands held (peak resident MiB, read every half second), its
attempts (more than one: its worker was lost and Ray tried again), the error line of a
failed item, the link to its run's ``report.html`` and log, and the run's figures: stage 1's
PSNR and mask IoU, stage 2's segments and ARI, and the full fit's row of the report's first
table (albedo, light, shadow and relighting figures; n/a without ground truth).
"""

from __future__ import annotations

import csv
import html
import io
import json
import time
from pathlib import Path

COLUMNS = ("name", "status", "seconds", "peak MiB", "attempts", "preset", "source", "error",
           "report", "log")


def run_figures(run: Path) -> tuple[dict, bool]:
    """(figures, reused) of a finished run folder (its ``summary.json``); reused: every
    stage was made by an earlier call. ({}, False) without a summary."""
    path = Path(run) / "summary.json"
    if not path.is_file():
        return {}, False
    summary = json.loads(path.read_text())
    stages = summary.get("stages") or []
    figures: dict = {}
    for stage in stages:
        metrics = stage.get("metrics") or {}
        if stage.get("name", "").startswith("Stage 1"):
            figures["geometry PSNR"] = metrics.get("psnr")
            figures["mask IoU"] = metrics.get("mask_iou")
        elif stage.get("name", "").startswith("Stage 2"):
            figures["segments"] = metrics.get("K")
            figures["ARI"] = metrics.get("ari")
    table = (summary.get("tables") or [{}])[0]
    columns = table.get("columns") or []
    full = next((r for r in table.get("rows") or [] if r and r[0] == "full"), None)
    if full is not None:
        figures.update(zip(columns[1:], full[1:], strict=False))
    reused = bool(stages) and all(s.get("seconds") is None for s in stages if "metrics" in s)
    return figures, reused


def _rows(out: Path, items, rows: dict) -> tuple[list[str], list[dict]]:
    """(figure columns in first-seen order, one flat row per item)."""
    figure_columns: list[str] = []
    flat = []
    for item in items:
        row = rows.get(item.name) or {"status": "pending", "seconds": None, "attempts": 0,
                                      "error": "", "figures": {}}
        for c in row["figures"]:
            if c not in figure_columns:
                figure_columns.append(c)
        report = Path(item.run) / "report.html"
        log = Path(item.folder) / "batch.log"
        flat.append({"name": item.name, "status": row["status"], "seconds": row["seconds"],
                     "peak MiB": row.get("peak_mib"), "attempts": row["attempts"],
                     "preset": item.preset, "source": item.source, "error": row["error"],
                     "report": str(report) if (out / report).is_file() else "",
                     "log": str(log) if (out / log).is_file() else "", **row["figures"]})
    return figure_columns, flat


def _csv_value(v) -> str:
    if v is None:
        return ""
    return repr(v) if isinstance(v, float) else str(v)


def _html_value(v) -> str:
    if v is None:
        return "n/a"
    return f"{v:.4g}" if isinstance(v, float) else html.escape(str(v))


def write_tables(out: Path, items, rows: dict) -> None:
    """``out/batch.csv`` and ``out/batch.html`` for ``items`` (rows: name -> the row the
    runner made; items without one are pending)."""
    from mi_shadowgs.io.atomic import write_text

    out = Path(out)
    figure_columns, flat = _rows(out, items, rows)
    columns = [*COLUMNS, *figure_columns]
    text = io.StringIO()
    writer = csv.writer(text, lineterminator="\n")
    writer.writerow(columns)
    for r in flat:
        writer.writerow([_csv_value(r.get(c)) for c in columns])
    write_text(out / "batch.csv", text.getvalue())
    write_text(out / "batch.html", _page(out, columns, flat))


def _page(out: Path, columns: list[str], flat: list[dict]) -> str:
    counts: dict[str, int] = {}
    for r in flat:
        counts[r["status"]] = counts.get(r["status"], 0) + 1
    shown = [c for c in columns if c not in ("report", "log", "source")]
    head = "".join(f"<th>{html.escape(c)}</th>" for c in shown)
    body = []
    for r in flat:
        cells = []
        for c in shown:
            value = r.get(c)
            if c == "name" and r["report"]:
                cell = f'<a href="{html.escape(r["report"])}">{html.escape(r["name"])}</a>'
            elif c == "status" and r["log"]:
                cell = f'<a href="{html.escape(r["log"])}">{html.escape(r["status"])}</a>'
            elif c in ("seconds", "peak MiB") and value is not None:
                cell = f"{value:.0f}"
            else:
                cell = "" if c == "error" and not value else _html_value(value)
            cells.append(f"<td>{cell}</td>")
        body.append(f'<tr class="{html.escape(r["status"])}">' + "".join(cells) + "</tr>")
    summary = ", ".join(f"{n} {s}" for s, n in sorted(counts.items()))
    return ("<!doctype html>\n<html><head><meta charset=\"utf-8\">"
            f"<title>batch {html.escape(out.name)}</title><style>"
            "body{font-family:sans-serif;margin:1.5em}table{border-collapse:collapse}"
            "td,th{border:1px solid #ccc;padding:.25em .5em;text-align:right}"
            "td:first-child,th:first-child{text-align:left}tr.failed{background:#fdd}"
            "tr.pending{color:#888}</style></head><body>"
            f"<h1>batch {html.escape(out.name)}</h1><p>{len(flat)} items: "
            f"{html.escape(summary)}; updated {time.strftime('%Y-%m-%d %H:%M:%S')}. "
            "The name links to the item's report, the status to its log.</p>"
            f"<table><tr>{head}</tr>\n" + "\n".join(body) + "\n</table></body></html>\n")
