"""The report of a real (tiny) run: every image and link it names exists, its plots are
byte-identical when written again, it survives missing files, and, where Chromium is
installed, a headless Chromium loads every image and the page fits a 1400-px window."""

from __future__ import annotations

import json
import re
import shutil
from html import unescape
from pathlib import Path

import pytest
from tiny_cli import TINY, presets

import mi_shadowgs.api as msg
from mi_shadowgs.io.images import read_png
from mi_shadowgs.io.report import render_html
from mi_shadowgs.pipeline import write_report_figures
from validation import report_page

CHROMIUM = report_page.find_chromium()
NO_CHROMIUM = report_page.NO_CHROMIUM + "; the page's layout is checked only where it is installed"


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
    assert per_view["columns"] == ["view", "image", "PSNR", "SSIM", "LPIPS"]
    assert [r[:2] for r in per_view["rows"][:3]] == [
        ["r_000", "albedo"], ["r_000", "sun_high"], ["r_000", "env_sky_envmap"]]
    assert len(per_view["rows"]) == 6
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


def test_report_reads_right(run):
    """The curves mark where stage 1's late loss terms start (from the run's recorded
    settings), a channel the preset holds constant says so, every grid thumbnail links to
    its image, and no grid header may break inside a word."""
    summary = json.loads((run / "summary.json").read_text())
    geo = json.loads((run / "geometry" / "config.json").read_text())["config"]
    curves = next(f for f in summary["stages"][0]["figures"]
                  if f["path"] == "report/geometry_curves.png")
    assert {m["setting"]: m["x"] for m in curves["markers"]} == {
        "normal_from": geo["normal_from"], "dist_from": geo["dist_from"]}
    assert summary["grids"][0]["column_notes"]["metallic"].startswith(
        "held at 0 by the preset")  # test-tiny, like cpu-small, has specular "off"
    page = (run / "report.html").read_text()
    assert "held at 0 by the preset" in page and "normal loss from iteration" in page
    thumbs = re.findall(r"<td>(<a href='[^']+'>)?<img src='([^']+)'", page)
    assert thumbs and all(link == f"<a href='{src}'>" for link, src in thumbs)
    assert "anywhere" not in page and "word-break: normal" in page
    assert "relit env_<wbr>sky_<wbr>envmap" in page  # breaks after "_", not inside words


@pytest.mark.skipif(CHROMIUM is None, reason=NO_CHROMIUM)
def test_report_in_headless_chromium(run, tmp_path):
    """The check ``make validate`` runs on every table run (validation.report_page)."""
    shot = tmp_path / "report.png"
    result = report_page.check_report(run / "report.html", shot)
    img = read_png(shot)
    assert img.shape[1] == report_page.PAGE_WIDTH
    assert img.std() > 10  # something was drawn, not a blank page
    # The page's images all load, nothing is wider than the window, no table hides columns
    # in a sideways scroll, and the grid's thumbnails are not drawn tiny.
    assert result["bad"] == [] and result["images"] >= 8
    assert result["width"] <= report_page.PAGE_WIDTH and result["ok"]
    assert result["wide_tables"] == [] and result["thumb_min_px"] >= 96
    # A page that is too wide, or with an image that does not load, is caught: the probe is
    # not a check that cannot fail.
    wide = tmp_path / "wide.html"
    wide.write_text("<html><head></head><body><div style='width:2000px'>x</div>"
                    "<img src='gone.png'></body></html>")
    bad = report_page.check_report(wide, tmp_path / "wide.png")
    assert bad["width"] > report_page.PAGE_WIDTH and bad["bad"] == ["gone.png"]
    assert not bad["ok"]
    scrolled = tmp_path / "scrolled.html"  # the page fits, the table hides its columns
    scrolled.write_text("<html><head></head><body><div style='overflow-x:auto'><table><tr>"
                        + "<th>env_sky_envmap_LPIPS</th>" * 80 + "</tr></table></div>"
                        "</body></html>")
    hidden = report_page.check_report(scrolled, tmp_path / "scrolled.png")
    assert hidden["width"] <= report_page.PAGE_WIDTH and len(hidden["wide_tables"]) == 1
    assert not hidden["ok"]
    with pytest.raises(AssertionError, match="wide.html"):
        report_page.run(tmp_path / "shots", [wide])
