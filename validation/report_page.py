"""The run reports in headless Chromium: each ``report.html`` is
screenshot at a 1400-px window, and a copy of the page reports after loading whether every
image loaded, how wide the page is, which tables reach past the window (a table that
scrolls inside its box hides columns) and how small the grid's thumbnails are drawn::

    python -m validation.report_page RUN [RUN ...] [--out SHOTS]

``make validate`` checks every run of the pipeline table this way (``validation.run_all``,
``report_pages``); ``tests/test_report_page.py`` uses the same check on a tiny run. Needs
``chromium`` (``scripts/setup.sh --chromium`` installs it when root).
"""

from __future__ import annotations

import argparse
import json
import re
import shutil
import subprocess
import tempfile
from html import unescape
from pathlib import Path

from mi_shadowgs.io.atomic import write_json
from validation import claim_out, fail

PAGE_WIDTH = 1400
NO_CHROMIUM = ("no chromium on PATH (Debian: apt-get install -y chromium, or "
               "scripts/setup.sh --chromium as root)")
# Appended to a copy of the page: after loading, the body carries what the check reads.
PROBE = """<script>window.addEventListener('load', () => {
  const bad = [...document.images].filter(i => !(i.complete && i.naturalWidth > 0));
  const page = document.documentElement.clientWidth;
  const wide = [...document.querySelectorAll('table')].filter(
    t => t.getBoundingClientRect().right > page + 1);
  const thumbs = [...document.querySelectorAll('table.grid img')].map(
    i => i.getBoundingClientRect().width);
  document.body.setAttribute('data-probe', JSON.stringify({
    width: document.documentElement.scrollWidth, images: document.images.length,
    bad: bad.map(i => i.getAttribute('src')),
    wide_tables: wide.map(t => t.rows[0] ? t.rows[0].textContent.slice(0, 60) : ''),
    thumb_min_px: thumbs.length ? Math.min(...thumbs) : null}));
});</script></body>"""


def find_chromium() -> str | None:
    return shutil.which("chromium") or shutil.which("chromium-browser") or \
        shutil.which("google-chrome")


def chromium(*args: str, width: int = PAGE_WIDTH) -> subprocess.CompletedProcess:
    exe = find_chromium()
    if exe is None:
        raise FileNotFoundError(NO_CHROMIUM)
    return subprocess.run([exe, "--headless", "--no-sandbox", "--disable-gpu",
                           "--hide-scrollbars", f"--window-size={width},3000", *args],
                          capture_output=True, text=True, timeout=120)


def probe(page: Path, width: int = PAGE_WIDTH) -> dict:
    """{"width": the page's scroll width, "images": count, "bad": srcs that did not load,
    "wide_tables": the first row's text of each table that reaches past the window,
    "thumb_min_px": the narrowest grid thumbnail's drawn width} of an HTML file that ends
    with ``PROBE``."""
    dom = chromium("--virtual-time-budget=10000", "--dump-dom", page.as_uri(),
                   width=width).stdout
    found = re.search(r"data-probe=\"([^\"]+)\"", dom)
    if not found:
        raise RuntimeError(f"{page}: Chromium gave no probe result: {dom[-500:]!r}")
    return json.loads(unescape(found.group(1)))


def check_report(report: Path, shot: Path, width: int = PAGE_WIDTH) -> dict:
    """Screenshot ``report`` into ``shot`` and probe a copy of it (its relative paths
    resolved against the run by ``<base>``, written in a temporary folder, so the run is
    not touched). Returns the probe's result plus ``ok`` and the screenshot's path."""
    report = Path(report).resolve()
    shot = Path(shot).resolve()
    shot.parent.mkdir(parents=True, exist_ok=True)
    proc = chromium(f"--screenshot={shot}", report.as_uri(), width=width)
    if not shot.is_file():
        raise RuntimeError(f"{report}: Chromium wrote no screenshot: {proc.stderr[-500:]}")
    page = report.read_text()
    with tempfile.TemporaryDirectory() as tmp:
        copy = Path(tmp) / "probe.html"
        copy.write_text(page.replace("<head>", f"<head><base href='{report.parent.as_uri()}/'>",
                                     1).replace("</body>", PROBE))
        result = probe(copy, width)
    result.update(ok=(not result["bad"] and not result["wide_tables"]
                      and result["width"] <= width and result["images"] > 0),
                  screenshot=str(shot), report=str(report))
    return result


def markdown(results: list[dict], width: int = PAGE_WIDTH) -> str:
    lines = ["## Report pages in headless Chromium", "",
             f"Each run's `report.html` at a {width}-px window: images loaded, page width.", "",
             "| report | images | not loaded | page width px | tables past the window | "
             "fits | screenshot |",
             "|---|---|---|---|---|---|---|"]
    for r in results:
        lines.append(f"| {r['report']} | {r['images']} | {len(r['bad'])} | {r['width']} | "
                     f"{len(r['wide_tables'])} | {'yes' if r['ok'] else '**no**'} | "
                     f"{r['screenshot']} |")
    return "\n".join(lines) + "\n"


def run(out_dir: Path, reports: list[Path]) -> dict:
    """Check every report; the screenshots go to ``out_dir``. Raises when one fails, so
    ``validation.run_all`` counts the validation as failed."""
    out_dir = Path(out_dir)
    if not reports:
        raise FileNotFoundError("no report.html to check (run the pipeline validation first)")
    results = []
    for rep in reports:
        name = "-".join(Path(rep).resolve().parent.parts[-2:]) + ".png"
        results.append(check_report(Path(rep), out_dir / name))
    md = markdown(results)
    out_dir.mkdir(parents=True, exist_ok=True)
    write_json(out_dir / "report_pages.json", results)
    bad = [r for r in results if not r["ok"]]
    if bad:
        raise AssertionError(f"{len(bad)} report page(s) fail: " + "; ".join(
            f"{r['report']}: width {r['width']} px, not loaded {r['bad'][:3]}, tables past "
            f"the window {r['wide_tables'][:3]}" for r in bad))
    return {"markdown": md, "results": results}


def main(argv=None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("runs", nargs="+", help="run folders (or their report.html)")
    ap.add_argument("--out", default="report-pages", help="folder for the screenshots")
    args = ap.parse_args(argv)
    claim_out(args.out, "validation.report_page", ('report_pages.json',))
    reports = [Path(r) / "report.html" if Path(r).is_dir() else Path(r) for r in args.runs]
    for rep in reports:
        if not rep.is_file():
            fail(f"{rep}: no report page")
    try:
        res = run(Path(args.out), reports)
    except AssertionError as exc:
        print(exc)
        return 1
    print(res["markdown"])
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
