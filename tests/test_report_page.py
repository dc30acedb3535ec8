"""The report of a real (tiny) run: every image and link it names exists, its plots are
byte-identical when written again, it survives missing files, and, where Chromium is
installed, a headless Chromium loads every image and the page fits a 1400-px window."""

from __future__ import annotations

import json
import re
import shutil
import subprocess
from html import unescape
from pathlib import Path

import pytest
from tiny_cli import TINY, presets

import mi_shadowgs.api as msg
from mi_shadowgs.io.images import read_png
from mi_shadowgs.io.report import render_html
from mi_shadowgs.pipeline import write_report_figures

PAGE_WIDTH = 1400
CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser") or \
    shutil.which("google-chrome")
NO_CHROMIUM = "no chromium on PATH (Debian: apt-get install -y chromium); the page's layout " \
              "is checked only where it is installed"


@pytest.fixture(scope="module")
def run(tmp_path_factory):
    root = tmp_path_factory.mktemp("report_page")
    with pytest.MonkeyPatch.context() as mp:
        for table, config in presets():
            mp.setitem(table, TINY, config)
        data = msg.generate_dataset(msg.scene_path("default"), root / "data", preset=TINY)
        msg.run(data, root / "run", preset=TINY)
    return root / "run"


def _refs(page: str) -> list[str]:
    return [unescape(r) for r in re.findall(r"(?:src|href)='([^']+)'", page)]


def test_every_image_and_link_of_the_report_exists(run):
    page = (run / "report.html").read_text()
    refs = _refs(page)
    assert "missing:" not in page
    for ref in refs:
        assert (run / ref).is_file(), ref
    images = [r for r in refs if r.endswith(".png")]
    for name in ("report/geometry_curves.png", "report/light_map.png",
                 "report/material_loss.png", "report/error_scale.png"):
        assert name in images
    assert all(read_png(run / r).size for r in images)
    summary = json.loads((run / "summary.json").read_text())
    cols = summary["grid"]["columns"]
    assert "albedo error" in cols and sum(c.startswith("relit ") and c.endswith(" error")
                                          for c in cols) >= 2  # directional and sky
    prov = {p["name"]: p["value"] for p in summary["provenance"]}
    assert prov["variant"] == "llvm_ad_rgb" and prov["Dr.Jit"] and prov["device"]
    titles = [t["title"] for t in summary["tables"]]
    speed = summary["tables"][titles.index("Render speed for 200 test views "
                                           "(paper Sec. V-A4)")]
    assert "extrapolated" in speed["note"]
    per_view = summary["tables"][titles.index("Per test view (full fit)")]
    assert [r[0] for r in per_view["rows"]] == ["r_000", "r_001"]
    hist = (run / "material" / "full" / "history.csv").read_text().splitlines()
    assert hist[0] == "step,loss" and len(hist) > 2
    manifest = json.loads((run / "material" / "full" / ".mi_shadowgs_manifest.json").read_text())
    assert "history.csv" in manifest["files"]


def test_report_plots_are_byte_identical_and_tolerate_missing_files(run, tmp_path):
    data = Path(json.loads((run / "summary.json").read_text())["dataset"])
    write_report_figures(tmp_path, run, data)
    for p in sorted(tmp_path.iterdir()):  # no date or version inside the PNGs
        assert p.read_bytes() == (run / "report" / p.name).read_bytes(), p.name
    bare = tmp_path / "bare"
    shutil.copytree(run, bare)
    (bare / "geometry" / "log.csv").unlink()
    (bare / "material" / "full" / "history.csv").unlink()
    shutil.rmtree(bare / "report")
    (bare / "report").mkdir()
    write_report_figures(bare / "report", bare, tmp_path / "no_dataset")
    assert sorted(p.name for p in (bare / "report").iterdir()) == \
        ["error_scale.png", "light_map.png"]  # the light map without ground truth
    page = render_html(json.loads((run / "summary.json").read_text()), bare)
    assert "missing: report/geometry_curves.png" in page  # named, not dropped


def _chromium(*args: str) -> subprocess.CompletedProcess:
    return subprocess.run([CHROMIUM, "--headless", "--no-sandbox", "--disable-gpu",
                           "--hide-scrollbars", f"--window-size={PAGE_WIDTH},3000", *args],
                          capture_output=True, text=True, timeout=120)


PROBE = """<script>window.addEventListener('load', () => {
  const bad = [...document.images].filter(i => !(i.complete && i.naturalWidth > 0));
  document.body.setAttribute('data-probe', JSON.stringify({
    width: document.documentElement.scrollWidth, images: document.images.length,
    bad: bad.map(i => i.getAttribute('src'))}));
});</script></body>"""


@pytest.mark.skipif(CHROMIUM is None, reason=NO_CHROMIUM)
def test_report_in_headless_chromium(run, tmp_path):
    shot = tmp_path / "report.png"
    proc = _chromium(f"--screenshot={shot}", (run / "report.html").as_uri())
    assert shot.is_file(), proc.stderr[-2000:]
    img = read_png(shot)
    assert img.shape[1] == PAGE_WIDTH
    assert img.std() > 10  # something was drawn, not a blank page
    # The page's images all load and nothing is wider than the window: a copy of the page
    # (its relative paths resolved against the run by <base>) reports both after loading.
    probe = tmp_path / "probe.html"
    page = (run / "report.html").read_text()
    probe.write_text(page.replace("<head>", f"<head><base href='{run.as_uri()}/'>", 1)
                     .replace("</body>", PROBE))
    result = _probe(probe)
    assert result["bad"] == [] and result["images"] >= 8
    assert result["width"] <= PAGE_WIDTH
    # A page that is too wide is caught: the probe is not a check that cannot fail.
    wide = tmp_path / "wide.html"
    wide.write_text("<html><body><div style='width:2000px'>x</div>" + PROBE + "</html>")
    assert _probe(wide)["width"] > PAGE_WIDTH


def _probe(page: Path) -> dict:
    dom = _chromium("--virtual-time-budget=10000", "--dump-dom", page.as_uri()).stdout
    found = re.search(r"data-probe=\"([^\"]+)\"", dom)
    assert found, dom[-2000:]
    return json.loads(unescape(found.group(1)))
