"""The run report: HTML from summary.json, its paging and notes, and its errors."""

from __future__ import annotations

import json

import numpy as np
import pytest

from mi_shadowgs import presets
from mi_shadowgs.io.images import write_png
from mi_shadowgs.io.report import GRID_PAGE_COLUMNS, _grid_pages, render_html, write_report
from mi_shadowgs.summary import (
    _held_channels,
    _per_view_tables,
    loss_term_starts,
    refresh_speed_error,
)


def test_report_shows_tables_grid_and_stage_figures(tmp_path):
    write_png(tmp_path / "a.png", np.full((4, 4, 3), 0.5))
    summary = {
        "title": "run <x>", "preset": "cpu-small", "total_seconds": 12.5,
        "tables": [{"title": "T1", "columns": ["variant", "albedo PSNR"],
                    "rows": [["full", 31.234567]], "note": "n"}],
        "grid": {"columns": ["input", "albedo"],
                 "rows": [{"label": "r_000", "cells": ["a.png", "missing.png"]}]},
        "stages": [{"name": "Stage 1", "seconds": 3.0, "metrics": {"psnr": 35.0},
                    "figures": [{"title": "preview", "path": "a.png"}]}],
    }
    (tmp_path / "summary.json").write_text(json.dumps(summary))
    page = write_report(tmp_path).read_text()
    assert page.count("<img src='a.png'") == 2  # the grid cell and the stage figure
    assert "missing: missing.png" in page  # a lost figure is named, not silently dropped
    assert "31.23" in page and "run &lt;x&gt;" in page  # numbers formatted, text escaped
    assert render_html({"stages": []}, tmp_path).startswith("<!doctype html>")


def test_report_errors_name_the_file(tmp_path):
    with pytest.raises(FileNotFoundError, match="summary.json"):
        write_report(tmp_path)
    (tmp_path / "summary.json").write_text("{not json")
    with pytest.raises(ValueError, match="summary.json: malformed JSON"):
        write_report(tmp_path)
    for summary, field in (({"stages": 5}, "stages"), ({"tables": [3]}, "tables")):
        (tmp_path / "summary.json").write_text(json.dumps(summary))
        assert not refresh_speed_error(tmp_path)  # leaves it for write_report to name
        with pytest.raises(ValueError, match=f"summary.json: field '{field}' must be a list"):
            write_report(tmp_path)


# The demo's Fig. 3 columns: input, then groups of a name, its ground truth and its error.
FIG3 = ["input", "albedo", "albedo (GT)", "albedo error", "roughness", "metallic", "normal",
        "irradiance", "irradiance (GT)", "visibility az 1 el 2", "segments",
        *[f"relit {n}{s}" for n in ("env_sky_envmap", "sun_high", "sun_low")
          for s in ("", " (GT)", " error")]]


def test_a_wide_grid_is_paged_by_groups_with_linked_thumbnails(tmp_path):
    write_png(tmp_path / "a.png", np.full((4, 4, 3), 0.5))
    pages = _grid_pages(FIG3)
    assert all(len(p) <= GRID_PAGE_COLUMNS and p[0] == 0 for p in pages) and len(pages) > 1
    assert sorted(i for p in pages for i in p[1:]) == list(range(1, len(FIG3)))
    for name in ("albedo", "relit sun_low"):  # a group is never split between pages
        assert len({k for k, p in enumerate(pages) for i in p if FIG3[i].startswith(name)}) == 1
    grid = {"columns": FIG3, "rows": [{"label": "r_000", "cells": ["a.png"] * len(FIG3)}],
            "column_notes": {"metallic": "held at 0 by the preset"}}
    page = render_html({"grid": grid, "stages": [{"name": "S", "figures": [
        {"title": "curves", "path": "a.png", "wide": True,
         "markers": [{"x": 5, "label": "normal loss from iteration 5 (normal_from)"}]}]}]},
        tmp_path)
    assert page.count("<table class='grid'>") == len(pages)
    # every column once, the input on every page, and the plot
    assert page.count("<a href='a.png'><img src='a.png'") == len(FIG3) + len(pages) - 1 + 1
    assert "metallic<div class='colnote'>held at 0 by the preset</div>" in page
    assert "curves; normal loss from iteration 5 (normal_from)</figcaption>" in page


def test_per_view_table_keeps_five_columns_for_any_number_of_relightings():
    per = {"psnr": [20.0, 21.0], "ssim": [0.9, 0.8], "lpips": [0.1, 0.2]}
    metrics = {"test_views": ["r_000", "r_001"], "albedo_per_view": per,
               "relighting": {f"light{k}": {"per_view": per} for k in range(6)}}
    (table,) = _per_view_tables(metrics)
    assert table["columns"] == ["view", "image", "PSNR", "SSIM", "LPIPS"]
    assert len(table["rows"]) == 2 * 7 and table["rows"][7] == ["r_001", "albedo", 21.0, 0.8,
                                                                 0.2]


def test_loss_term_starts_and_held_channels_read_the_recorded_settings(tmp_path):
    (tmp_path / "geometry").mkdir()
    geo = {"iterations": 100, "lambda_normal": 0.05, "normal_from": 40, "lambda_dist": 0.0,
           "dist_from": 30}
    (tmp_path / "config.json").write_text(json.dumps({"geometry": geo}))
    assert [m["setting"] for m in loss_term_starts(tmp_path)] == ["normal_from"]  # dist: 0
    (tmp_path / "geometry" / "config.json").write_text(json.dumps(
        {"config": dict(geo, lambda_dist=1.0, normal_from=100)}))  # preferred; 100: not run
    assert loss_term_starts(tmp_path) == [
        {"x": 30, "setting": "dist_from", "label": "distortion loss from iteration 30 "
                                                   "(dist_from)"}]
    off, auto = presets.get_config("cpu-small"), presets.get_config("paper")
    assert off.material.specular == "off" and auto.material.specular == "auto"
    assert _held_channels({"full": {"specular": False}}, off)["metallic"].startswith(
        "held at 0 by the preset")
    assert "dropped" in _held_channels({"full": {"specular": False}}, auto)["metallic"]
    assert _held_channels({"full": {"specular": True}}, auto) == {}
