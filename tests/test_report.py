"""The run report: HTML from summary.json, and its errors."""

from __future__ import annotations

import json

import numpy as np
import pytest

from mi_shadowgs.io.images import write_png
from mi_shadowgs.io.report import render_html, write_report
from mi_shadowgs.summary import refresh_speed_error


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
