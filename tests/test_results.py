"""RESULTS.md (and docs/results.md) are generated from the committed result files in
``results/`` (``make results``): current, the same bytes on every run, and each section
names its command, machine, commit and date."""

from __future__ import annotations

import json
from pathlib import Path

import pytest

from scripts import results

ROOT = Path(__file__).resolve().parents[1]


def test_results_pages_are_current():
    text = results.render(ROOT / "results")
    for page in (ROOT / "RESULTS.md", ROOT / "docs" / "results.md"):
        assert page.read_text(encoding="utf-8") == text, f"{page} is stale: run make results"
    assert results.main(["--check"]) == 0


def test_rendering_twice_gives_the_same_bytes(tmp_path):
    out = [str(tmp_path / "a.md"), str(tmp_path / "b.md")]
    assert results.main(["--out", *out]) == 0
    first = Path(out[0]).read_bytes()
    assert results.main(["--out", *out]) == 0
    assert Path(out[0]).read_bytes() == first == Path(out[1]).read_bytes()


def test_every_result_file_records_where_its_figures_come_from():
    files = sorted((ROOT / "results").glob("*.json"))
    assert len(files) >= 6
    for path in files:
        doc = json.loads(path.read_text(encoding="utf-8"))
        for key in ("title", "command", "machine", "commit", "date", "produced_by", "tables"):
            assert doc.get(key), f"{path.name}: no {key}"
    # One page of current figures: about 33 lines a section (ten sections, 330 lines).
    lines = len((ROOT / "RESULTS.md").read_text().splitlines())
    assert lines <= 33 * len(files), f"RESULTS.md has {lines} lines for {len(files)} sections"


def test_a_row_of_the_wrong_width_is_refused(tmp_path):
    (tmp_path / "x.json").write_text(json.dumps(
        {"title": "x", "tables": [{"columns": ["a", "b"], "rows": [["1"]]}]}))
    with pytest.raises(ValueError, match="1 cells under 2 columns"):
        results.load(tmp_path)


def test_the_check_fails_on_a_stale_page(tmp_path):
    page = tmp_path / "R.md"
    page.write_text("old\n")
    assert results.main(["--out", str(page), "--check"]) == 1
    assert page.read_text() == "old\n"


def test_bench_and_validate_results_have_the_schema(tmp_path):
    raster = {"table": [{"res": 128, "n": 20000, "ours_fwd_bwd_ms": 22.8,
                         "mitsuba_fwd_bwd_ms": 480.1, "ratio_fwd_bwd": 21.06,
                         "ours_peak_rss_mb": 154, "mitsuba_peak_rss_mb": 159}]}
    machine = {"cpu_model": "CPU", "cpu_count": 2, "variant": "llvm_ad_rgb", "mitsuba": "3.9.1",
               "drjit": "1.5.0", "commit": "abcdef0123", "date_utc": "2026-11-24 19:31 UTC"}
    doc = results.raster_result(raster, machine, "python -m benchmarks.run_all --out B")
    assert doc["tables"][0]["rows"] == [["128^2", "20,000", "22.8", "480.1", "21.1x", "154",
                                         "159"]]
    assert (doc["commit"], doc["date"]) == ("abcdef0", "2026-11-24")
    # validation.pipeline's rows (pipeline.json): each variant's metrics under "variants"
    rows = [{"scene": "toy_train", "lights": "low", "seed": s, "commit": "c0ffee0123",
             "variants": {"full": {"shadow_iou": 0.8 + s / 100, "shadow_iou_decided": 0.81,
                                   "albedo_psnr": 50.0, "relight_psnr": 30.0,
                                   "light_cosine": 0.999, "angular_error_deg": [0.25, 1.0]},
                          "no_visibility": {"shadow_iou": 0.1}}} for s in (1, 0)]
    pipe = results.pipeline_result(rows, "python -m validation.run_all", "CPU", "2026-11-29")
    assert pipe["tables"][0]["rows"] == [
        ["toy train-low", "0.800 / 0.810", "0.810 / 0.810", "50.00 / 50.00", "30.00 / 30.00",
         "0.999 / 0.999", "0.2/1.0; 0.2/1.0"],
        ["**mean (1)**", "**0.800 / 0.810**", "0.810 / 0.810", "50.00 / 50.00",
         "30.00 / 30.00", "0.999 / 0.999", ""]]
    assert pipe["commit"] == "c0ffee0"
    for i, made in enumerate((doc, pipe)):
        results.write_result(tmp_path / f"r{i}.json", made)
    text = results.render(tmp_path)
    assert "toy train-low" in text and "21.1x" in text
