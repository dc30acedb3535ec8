"""Smoke test of ``benchmarks.profile_step`` on tiny data: every part of each step is in the
table and the JSON, and the parts' shares add up to the instrumented step."""

from __future__ import annotations

import json

import pytest

from benchmarks import profile_step

STAGE1_PARTS = {"rasterize forward", "rasterize backward (tiled)", "D-SSIM forward",
                "losses (L1, mask, normal, dist, mse)", "backward (losses, D-SSIM, SH, glue)",
                "optimiser (Adam)", "densify statistics", "densify/prune (1 in 100 steps)"}
STAGE4_PARTS = {"visibility (shadow-map lookups)", "shade (BRDF x lights)",
                "splat material maps", "backward", "optimiser (Adam)", "clamp channels"}


def test_quick_profile(tmp_path):
    report = profile_step.main(["--quick", "--out", str(tmp_path), "--results",
                                str(tmp_path / "results")])
    md = (tmp_path / "profile.md").read_text()
    saved = json.loads((tmp_path / "profile.json").read_text())
    assert saved["machine"]["command"].startswith("python -m benchmarks.profile_step")
    assert saved["machine"]["commit"] and saved["machine"]["drjit"]
    (case,) = report["cases"].values()
    stages = {k: v for k, v in case.items() if k.startswith("stage")}
    assert len(stages) == 3
    for stage, r in stages.items():
        parts = r["parts"]
        assert set(parts) >= (STAGE1_PARTS if stage == "stage 1" else STAGE4_PARTS)
        total = sum(p["ms"] for p in parts.values())
        shares = [p["ms"] / total for p in parts.values()]
        assert sum(shares) == pytest.approx(1.0, abs=1e-9)
        assert r["plain_ms"] > 0 and all(p["ms"] >= 0 for p in parts.values())
        # Kernels come from Dr.Jit's history: the rasterizer and the backward launch some.
        assert parts["backward" if stage != "stage 1" else "rasterize forward"]["kernels"] > 0
        for name in parts:
            assert f"| {name} |" in md
    # The shares printed in the table add up to ~100% (rounded to 0.1% each).
    for block in md.split("## ")[1:]:
        rows = [ln.split("|") for ln in block.splitlines() if ln.startswith("| ")
                and not ln.startswith(("| part", "| **", "| step as"))]
        assert sum(float(r[3].strip().rstrip("%")) for r in rows) == pytest.approx(100, abs=2)
    assert saved["cases"] and saved["steps"] == report["steps"]
    # --results: the schema make results renders; --baseline: an earlier profile's times
    # beside this run's (here the same run's, so every speed-up is 1.00x).
    from scripts.results import REQUIRED

    doc = json.loads((tmp_path / "results" / "step_profile.json").read_text())
    assert all(k in doc for k in REQUIRED) and len(doc["tables"]) == 1
    assert str(tmp_path) not in doc["command"] and "--results results" in doc["command"]
    compared = profile_step.result_doc(saved, saved)
    commit = saved["machine"]["commit"]
    (t,) = compared["tables"]
    assert t["columns"][2:4] == [f"ms at {commit}"] * 2
    assert all(len(r) == len(t["columns"]) for r in t["rows"])
    inst = [r for r in t["rows"] if r[1] == "**step (instrumented)**"]
    assert len(inst) == 3 and all(r[2] == r[3] for r in inst)
    with pytest.raises(SystemExit):
        profile_step.main(["--quick", "--baseline", str(tmp_path / "none.json")])

