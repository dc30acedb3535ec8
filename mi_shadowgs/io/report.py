"""The run report: one self-contained HTML page plus PNG figures.

The pipeline records what each stage produced in ``RUN/summary.json``::

    {"title": ..., "dataset": ..., "preset": ..., "variant": ..., "date": ...,
     "total_seconds": ..., "reused_stages": [...names of stages an earlier call made...],
     "stages": [{"name": ..., "seconds": ..., "metrics": {...},
                 "figures": [{"title": ..., "path": "relative/to/RUN.png"}]}],
     "tables": [{"title": ..., "columns": [...], "rows": [[...], ...], "note": ...}],
     "grid": {"columns": [...], "rows": [{"label": ..., "cells": ["path", ...]}],
              "note": ..., "legend": "path.png"},
     "grids": [...more grids like "grid", shown after it...],
     "provenance": [{"name": ..., "value": ..., "href": "optional/link"}]}

A figure with ``"wide": true`` is a plot shown at its own size (up to the page's width);
others are pixel images shown enlarged, each a link to the image at full size. A figure's
``"markers"`` (``[{"x", "label", ...}]``, what its plot marks) are named in its caption. A
grid's ``"column_notes"`` (``{column: text}``) are shown under those columns' headers, for a
column whose images say nothing by themselves (a channel the preset holds constant).

The page fits a 1400-px window: a grid of more than ``GRID_PAGE_COLUMNS`` columns is shown as
several grids (each with the ``input`` column again, split between groups of columns such as
``albedo``, ``albedo (GT)``, ``albedo error``), headers break between words or after ``_``,
never inside a word, and a table wider than the page scrolls inside its box.

and this module turns it into ``RUN/report.html``. It knows nothing about the stages, so a
stage adds figures or metrics without touching the report.
"""

from __future__ import annotations

import html
import json
import os
from pathlib import Path

from mi_shadowgs.io.atomic import write_text

_CSS = """
* { box-sizing: border-box; }
body { font-family: system-ui, sans-serif; margin: 1.5em auto; padding: 0 1em;
       max-width: 1360px; color: #222; }
img { max-width: 100%; height: auto; }
h1 { font-size: 1.6em; } h2 { margin-top: 1.6em; border-bottom: 1px solid #ccc; }
table { border-collapse: collapse; margin: 0.6em 0; max-width: 100%; }
td, th { border: 1px solid #ccc; padding: 0.25em 0.6em; text-align: right;
         overflow-wrap: normal; word-break: normal; hyphens: manual; }
th { background: #f3f3f3; } td:first-child, th:first-child { text-align: left; }
.scroll { overflow-x: auto; max-width: 100%; }
figure { display: inline-block; margin: 0.3em; text-align: center; vertical-align: top; }
figure img { image-rendering: pixelated; width: 192px; border: 1px solid #ddd; }
figure.plot { display: block; }
figure.plot img { image-rendering: auto; width: auto; max-width: 100%; border: none; }
figcaption { font-size: 0.8em; }
table.grid { table-layout: fixed; width: 100%; }
table.grid td, table.grid th { padding: 1px; font-size: 0.75em; text-align: center; }
table.grid th:first-child { width: 4.5em; }
.grid img { width: 100%; max-width: 160px; image-rendering: pixelated; display: block;
            margin: auto; }
.colnote { font-weight: normal; color: #a33; }
.note { color: #666; font-size: 0.9em; }
"""


def _fmt(v) -> str:
    if v is None:  # a metric that was not computed (the table's note says why)
        return "n/a"
    if isinstance(v, float):
        if v != v:  # NaN
            return "n/a"
        return f"{v:.4g}" if abs(v) < 1e4 else f"{v:.3e}"
    if isinstance(v, (list, tuple)):
        return ", ".join(_fmt(x) for x in v)
    return html.escape(str(v))


def _img(run: Path, rel: str, alt: str, link: bool = False) -> str:
    """An image of the run; ``link``: wrapped in a link to the file, so that a thumbnail
    opens at full size."""
    if not (run / rel).is_file():
        return f"<span class='note'>missing: {html.escape(rel)}</span>"
    img = f"<img src='{html.escape(rel)}' alt='{html.escape(alt)}'>"
    return f"<a href='{html.escape(rel)}'>{img}</a>" if link else img


GRID_PAGE_COLUMNS = 10  # image columns of one grid table: wider grids are split


def _header(text: str) -> str:
    """A header's text, escaped, free to break after ``_`` (``env_sky_envmap``) as between
    words, and nowhere inside a word."""
    return html.escape(text).replace("_", "_<wbr>")


def _grid_pages(columns: list[str]) -> list[list[int]]:
    """The column indices of each table of a grid: at most ``GRID_PAGE_COLUMNS`` each, a
    leading ``input`` column repeated on every one, a group of columns that share a name
    (``x``, ``x (GT)``, ``x error``) kept together."""
    lead = [0] if columns and columns[0] == "input" else []
    groups: list[tuple[str, list[int]]] = []
    for i in range(len(lead), len(columns)):
        base = columns[i].removesuffix(" error").removesuffix(" (GT)")
        if groups and base == groups[-1][0]:
            groups[-1][1].append(i)
        else:
            groups.append((base, [i]))
    pages: list[list[int]] = []
    for _, idx in groups:
        if pages and len(pages[-1]) + len(idx) <= GRID_PAGE_COLUMNS:
            pages[-1] += idx
        else:
            pages.append(lead + idx)
    return pages or [lead]


def _grid_html(grid: dict, run: Path) -> list[str]:
    out = [f"<h2>{html.escape(grid.get('title', 'Decomposition and relighting'))}</h2>"]
    notes = grid.get("column_notes") or {}
    for idx in _grid_pages(grid["columns"]):
        cols = [grid["columns"][i] for i in idx]
        out.append("<table class='grid'><tr><th></th>")
        out.extend(f"<th>{_header(c)}" + (f"<div class='colnote'>{html.escape(notes[c])}</div>"
                                          if c in notes else "") + "</th>" for c in cols)
        out.append("</tr>")
        for row in grid["rows"]:
            cells = "".join(f"<td>{_img(run, row['cells'][i], c, link=True)}</td>"
                            if row["cells"][i] else "<td></td>" for i, c in zip(idx, cols,
                                                                                strict=True))
            out.append(f"<tr><th>{html.escape(row['label'])}</th>{cells}</tr>")
        out.append("</table>")
    if grid.get("legend"):
        out.append(f"<figure class='plot'>{_img(run, grid['legend'], 'error scale')}</figure>")
    if grid.get("note"):
        out.append(f"<p class='note'>{html.escape(grid['note'])}</p>")
    return out


# The header's rows: summary key -> label. A resumed run's seconds are its last call's.
_INFO_LABELS = {"dataset": "dataset", "preset": "preset", "variant": "variant", "date": "date",
                "total_seconds": "seconds (this call)",
                "reused_stages": "stages made by an earlier call"}


def render_html(summary: dict, run: Path) -> str:
    """The report page for ``summary`` (see module docstring); image paths relative to run."""
    title = summary.get("title", "mi_shadowgs run")
    out = [f"<!doctype html><html><head><meta charset='utf-8'><title>{html.escape(title)}"
           f"</title><style>{_CSS}</style></head><body><h1>{html.escape(title)}</h1>"]
    info = {label: summary[k] for k, label in _INFO_LABELS.items() if summary.get(k) not in
            (None, [])}
    if info:
        out.append("<table>" + "".join(f"<tr><th>{html.escape(k)}</th><td>{_fmt(v)}</td></tr>"
                                       for k, v in info.items()) + "</table>")
    prov = summary.get("provenance") or []
    if prov:
        out.append("<h2>Provenance</h2><table>")
        for item in prov:
            value = _fmt(item.get("value"))
            if item.get("href"):
                value = f"<a href='{html.escape(item['href'])}'>{value}</a>"
            out.append(f"<tr><th>{html.escape(str(item.get('name', '')))}</th>"
                       f"<td>{value}</td></tr>")
        out.append("</table>")
    for table in summary.get("tables", []):
        out.append(f"<h2>{html.escape(table['title'])}</h2><div class='scroll'><table><tr>")
        out.extend(f"<th>{_header(str(c))}</th>" for c in table["columns"])
        out.append("</tr>")
        for row in table["rows"]:
            out.append("<tr>" + "".join(f"<td>{_fmt(v)}</td>" for v in row) + "</tr>")
        out.append("</table></div>")
        if table.get("note"):
            out.append(f"<p class='note'>{html.escape(table['note'])}</p>")
    for grid in [summary.get("grid")] + list(summary.get("grids") or []):
        if grid and grid.get("rows"):
            out.extend(_grid_html(grid, run))
    for stage in summary.get("stages", []):
        secs = stage.get("seconds")
        head = html.escape(stage["name"]) + (f" <small>({secs:.1f} s)</small>" if secs else "")
        out.append(f"<h2>{head}</h2>")
        metrics = stage.get("metrics") or {}
        if metrics:
            out.append("<table>" + "".join(
                f"<tr><th>{html.escape(k)}</th><td>{_fmt(v)}</td></tr>"
                for k, v in metrics.items()) + "</table>")
        for fig in stage.get("figures", []):
            kind = " class='plot'" if fig.get("wide") else ""
            caption = fig["title"] + "".join(f"; {m['label']}" for m in fig.get("markers", []))
            out.append(f"<figure{kind}>{_img(run, fig['path'], fig['title'], link=True)}"
                       f"<figcaption>{html.escape(caption)}</figcaption></figure>")
        if stage.get("note"):
            out.append(f"<p class='note'>{html.escape(stage['note'])}</p>")
    out.append("</body></html>\n")
    return "".join(out)


def read_summary(path: Path) -> dict:
    """``RUN/summary.json``: a ValueError naming the file and field where it is not the
    object the page is made from (its ``stages`` and ``tables``, lists of objects)."""
    try:
        summary = json.loads(path.read_text())
    except json.JSONDecodeError as exc:
        raise ValueError(f"{path}: malformed JSON: {exc}") from None
    if not isinstance(summary, dict):
        raise ValueError(f"{path}: expected a JSON object at the top level")
    for field in ("stages", "tables"):
        value = summary.get(field, [])
        if not isinstance(value, list) or not all(isinstance(v, dict) for v in value):
            raise ValueError(f"{path}: field {field!r} must be a list of objects")
    return summary


def write_report(run: str | os.PathLike) -> Path:
    """Write ``RUN/report.html`` from ``RUN/summary.json``; returns the page's path."""
    run = Path(run)
    path = run / "summary.json"
    if not path.is_file():
        raise FileNotFoundError(f"{path}: no run summary (run `mi-shadowgs run` first)")
    summary = read_summary(path)
    page = run / "report.html"
    write_text(page, render_html(summary, run))
    return page
