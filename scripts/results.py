"""RESULTS.md from the committed result files in ``results/`` (``make results``).

Each ``results/*.json`` records one measurement: its figures (one or more tables), the
command that produced them, the machine, the commit and the date. This module renders them,
in their ``order``, into one page: ``RESULTS.md``, and the same text as the documentation
site's ``docs/results.md``. The output depends on the files alone, so running it twice gives
the same bytes; ``--check`` exits 1 when either page is not what the files give.

``make bench`` and ``make validate`` write files of the same schema with ``--results DIR``
(``raster_result`` and ``pipeline_result`` below)::

    python -m scripts.results [--results results] [--out RESULTS.md docs/results.md]
                              [--check]

Schema of a result file (keys other than ``title`` and ``tables`` are optional)::

    {"order": 1, "title": "...", "command": "...", "produced_by": "...", "machine": "...",
     "commit": "...", "date": "YYYY-MM-DD", "text": ["paragraph", ...],
     "tables": [{"caption": "...", "columns": ["a", "b"], "rows": [["1", "2"], ...]}],
     "notes": ["bullet", ...]}
"""

from __future__ import annotations

import argparse
import json
import sys
from pathlib import Path

ROOT = Path(__file__).resolve().parents[1]
HEADER = """# Results

The current figures of mi_shadowgs, one section per measurement. Each section names the
command that produced it, the machine, the commit and the date. This page is generated from
the files in `results/` by `make results`; do not edit it by hand. Why each default is
what it is, with the measurement that decided it: `docs/decisions.md`.
"""
REQUIRED = ("title", "tables")


def load(results: Path) -> list[dict]:
    """The result files under ``results``, in their ``order`` (then by file name)."""
    docs = []
    for path in sorted(Path(results).glob("*.json")):
        doc = json.loads(path.read_text(encoding="utf-8"))
        missing = [k for k in REQUIRED if k not in doc]
        if missing:
            raise ValueError(f"{path}: missing {', '.join(missing)}")
        for i, table in enumerate(doc["tables"]):
            width = len(table["columns"])
            for row in table["rows"]:
                if len(row) != width:
                    raise ValueError(f"{path}: table {i}: a row of {len(row)} cells "
                                     f"under {width} columns: {row}")
        docs.append({**doc, "_file": path.name})
    return sorted(docs, key=lambda d: (d.get("order", 99), d["_file"]))


def table_markdown(table: dict) -> list[str]:
    lines = []
    if table.get("caption"):
        lines += [table["caption"], ""]
    lines.append("| " + " | ".join(table["columns"]) + " |")
    lines.append("|" + "---|" * len(table["columns"]))
    lines += ["| " + " | ".join(str(c) for c in row) + " |" for row in table["rows"]]
    return lines + [""]


def section(doc: dict) -> list[str]:
    lines = [f"## {doc['title']}", ""]
    meta = [("Command", doc.get("command"), True), ("Machine", doc.get("machine"), False),
            ("Commit", doc.get("commit"), True), ("Date", doc.get("date"), False),
            ("Written by", doc.get("produced_by"), True)]
    for label, value, code in meta:
        if value:
            lines.append(f"- {label}: " + (f"`{value}`" if code else value))
    lines.append(f"- File: `results/{doc['_file']}`")
    lines.append("")
    for paragraph in doc.get("text", []):
        lines += [paragraph, ""]
    for table in doc["tables"]:
        lines += table_markdown(table)
    if doc.get("notes"):
        lines += [f"- {note}" for note in doc["notes"]] + [""]
    return lines


def render(results: Path) -> str:
    lines = [HEADER]
    for doc in load(results):
        lines += section(doc)
    return "\n".join(lines).rstrip("\n") + "\n"


def write_result(path: Path, doc: dict) -> None:
    """One result file, with sorted keys and a final newline (stable bytes)."""
    path = Path(path)
    path.parent.mkdir(parents=True, exist_ok=True)
    text = json.dumps(doc, indent=2, sort_keys=True, ensure_ascii=False) + "\n"
    tmp = path.with_name(f".{path.name}.tmp")
    tmp.write_text(text, encoding="utf-8")
    tmp.replace(path)


def raster_result(summary: dict, machine: dict, command: str) -> dict:
    """The rasterizer-against-Mitsuba result from ``bm_raster``'s ``raster.json`` and
    ``benchmarks.run_all``'s ``machine.json``."""
    rows = []
    for t in sorted(summary.get("table", []), key=lambda t: (t["res"], t["n"])):
        ratio = t.get("ratio_fwd_bwd")
        rows.append([f"{t['res']}^2", f"{t['n']:,}", _fmt(t.get("ours_fwd_bwd_ms"), 1),
                     _fmt(t.get("mitsuba_fwd_bwd_ms"), 1),
                     "-" if ratio is None else f"{ratio:.1f}x",
                     _fmt(t.get("ours_peak_rss_mb"), 0), _fmt(t.get("mitsuba_peak_rss_mb"), 0)])
    return {
        "order": 2, "title": "Rasterizer against Mitsuba's Gaussian renderer",
        "command": command, "produced_by": "make bench BENCH_ARGS=\"--results results\"",
        "machine": f"{machine.get('cpu_model')}, {machine.get('cpu_count')} cores, "
                   f"{machine.get('variant')}, Mitsuba {machine.get('mitsuba')} / "
                   f"Dr.Jit {machine.get('drjit')}",
        "commit": str(machine.get("commit", "unknown"))[:7],
        "date": str(machine.get("date_utc", ""))[:10],
        "tables": [{"columns": ["res", "surfels", "ours fwd+bwd ms", "Mitsuba fwd+bwd ms",
                                "Mitsuba / ours", "ours peak RSS MB", "Mitsuba peak RSS MB"],
                    "rows": rows}],
    }


PIPELINE_KEYS = (("shadow IoU", "shadow_iou", 3), ("shadow IoU (decided)",
                                                   "shadow_iou_decided", 3),
                 ("albedo dB", "albedo_psnr", 2), ("relight dB", "relight_psnr", 2),
                 ("light cos", "light_cosine", 3))


def _full_metrics(row: dict) -> dict:
    """A pipeline row's figures: its ``full`` variant's metrics (``validation.pipeline``
    nests each variant's under ``variants``), or the row itself where they are flat."""
    return row.get("variants", {}).get("full", row)


def _light_errors(metrics: dict) -> str:
    errs = metrics.get("angular_error_deg")
    return "-" if not errs else "/".join(f"{e:.1f}" for e in errs)


def pipeline_result(rows: list[dict], command: str, machine: str, date: str) -> dict:
    """The six-scene table from ``validation.pipeline``'s rows (its ``pipeline.json``): one
    table row per scene and light pair, each cell its seeds' figures joined by " / "; the
    light errors (each true light's, degrees) joined by "; "."""
    by_row: dict[str, list[dict]] = {}
    for r in rows:
        name = f"{r['scene'].replace('_', ' ')}-{r.get('lights', 'tuned')}"
        by_row.setdefault(name, []).append(r)
    table = []
    for name, runs in by_row.items():
        runs = [_full_metrics(r) for r in sorted(runs, key=lambda r: r.get("seed", 0))]
        table.append([name] + [" / ".join(_fmt(m.get(key), digits) for m in runs)
                               for _, key, digits in PIPELINE_KEYS]
                     + ["; ".join(_light_errors(m) for m in runs)])
    seeds = sorted({r.get("seed", 0) for r in rows})
    means = [" / ".join(_fmt(sum(_full_metrics(r)[key] for r in rows if r.get("seed", 0) == s)
                             / sum(1 for r in rows if r.get("seed", 0) == s), digits)
                        for s in seeds) for _, key, digits in PIPELINE_KEYS]
    table.append([f"**mean ({len(by_row)})**", f"**{means[0]}**", *means[1:], ""])
    commits = sorted({str(r.get("commit", "unknown"))[:7] for r in rows})
    presets = sorted({str(r.get("preset", "cpu-small")) for r in rows})
    return {
        "order": 1, "title": "Six scenes x two light pairs (paper Tables 1 and 3)",
        "command": command, "produced_by": "make validate VALIDATE_ARGS=\"--results results\"",
        "machine": machine, "commit": ", ".join(commits), "date": date,
        "text": [f"Preset `{', '.join(presets)}`; seeds {', '.join(map(str, seeds))} "
                 "(each cell: one figure per seed, joined by \" / \")."],
        "tables": [{"columns": ["row"] + [label for label, _, _ in PIPELINE_KEYS]
                    + ["light err deg"], "rows": table}],
    }


def lab_result(record: dict, machine: str) -> dict:
    """The lab captures' acceptance table from ``validation.lab``'s ``lab.json``: one row
    per scene and lamp distance, each figure as "control / lab" where both have it."""
    def pair(case, key, digits):
        return " / ".join(_fmt(case[k].get("scores", {}).get(key), digits)
                          for k in ("control", "lab"))

    def first(seq, digits):
        return _fmt(seq[0] if seq else None, digits)

    def gain(case):
        g = case["lab"].get("gains")
        return _fmt(g["global"]["max"] if g and "global" in g else None, 3)

    def minutes(case):
        return " / ".join(_fmt(None if case[k]["times"].get("run_s") is None else
                               case[k]["times"]["run_s"] / 60, 0) for k in ("control", "lab"))

    verdicts = {True: "pass", False: "fail", None: "not measured"}
    rows = []
    for case in record["cases"]:
        lab = case["lab"].get("scores", {})
        pos = lab.get("lamp_position_error")
        rows.append([f"{case['scene']}, {case['distance']:g} radii",
                     "directional" if pos and pos[0] is None else first(pos, 3),
                     " / ".join(first(case[k].get("scores", {}).get(
                         "light_angular_errors_deg"), 1) for k in ("control", "lab")),
                     pair(case, "strongest_light_share", 2), pair(case, "fitted_lights", 0),
                     pair(case, "shadow_iou", 3), pair(case, "albedo_psnr", 2), gain(case),
                     pair(case, "relight_psnr", 2),
                     _fmt(((lab.get("relighting") or {}).get("lamp_moved") or {}).get("psnr"),
                          2), minutes(case),
                     verdicts[case["passed"]]])
    s = record["settings"]
    return {
        "order": 5, "title": "Lab captures: a lamp in a room against its ideal control",
        "command": record["command"], "produced_by": "python -m validation.lab ... --results "
        "results", "machine": machine, "commit": str(record.get("commit", "unknown"))[:12],
        "date": record.get("date", ""),
        "text": [f"Preset `{s['preset']}`; {s['views']} photos of {s['photo_size'][0]}x"
                 f"{s['photo_size'][1]} on the mat, imported with SfM at {s['max_size']} px; "
                 "the lab capture: a sphere lamp of radius 0.15 radii, room light, +-0.35 EV "
                 "and +-4% white balance per photo, sensor noise, JPEG; the control: one "
                 "directional light of the lamp's direction and irradiance, nothing else. "
                 "Bounds: position <= 0.05 of the distance, direction <= 2 deg, strongest "
                 "light >= 0.90, shadow IoU and albedo at most 0.05 and 1 dB below the "
                 "control's, gains <= 0.03."],
        "tables": [{"columns": ["case", "lamp position err (share)",
                                "light err deg (control / lab)", "strongest light share",
                                "lights kept", "shadow IoU", "albedo dB",
                                "gain err (one scale)", "relight dB",
                                "lab relight dB, new point lamp", "run min", "bounds"],
                    "rows": rows}],
    }


def _fmt(value, digits: int) -> str:
    if value is None:
        return "-"
    try:
        return f"{float(value):.{digits}f}"
    except (TypeError, ValueError):
        return str(value)


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description="Write RESULTS.md from results/*.json.")
    ap.add_argument("--results", default=str(ROOT / "results"), help="the result files' folder")
    ap.add_argument("--out", nargs="+", default=[str(ROOT / "RESULTS.md"),
                                                 str(ROOT / "docs" / "results.md")],
                    help="the pages to write (each gets the same text)")
    ap.add_argument("--check", action="store_true",
                    help="write nothing; exit 1 when the page differs from the files")
    args = ap.parse_args(argv)
    text = render(Path(args.results))
    stale = []
    for out in map(Path, args.out):
        current = out.read_text(encoding="utf-8") if out.is_file() else None
        if current == text:
            continue
        stale.append(out)
        if not args.check:
            out.write_text(text, encoding="utf-8")
            print(f"wrote {out} from {args.results}")
    if args.check and stale:
        print(f"not current: {', '.join(map(str, stale))}: run make results", file=sys.stderr)
        return 1
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
