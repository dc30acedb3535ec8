"""``validation.lamp_cues``: how far a lamp's shadows and shading move when it moves."""

from __future__ import annotations

import json
import math

import numpy as np
import pytest

from mi_shadowgs.dataset.scene import Light
from validation import lamp_cues


def _half_plane(shift: float, angle_deg: float, size: int = 200) -> np.ndarray:
    """[1, size, size] pixels whose centres lie on one side of a line at ``angle_deg``
    through the image's centre, moved ``shift`` pixels along its normal."""
    y, x = np.mgrid[0:size, 0:size] + 0.5
    a = math.radians(angle_deg)
    n = np.array([math.cos(a), math.sin(a)])
    return ((x - size / 2) * n[0] + (y - size / 2) * n[1] > shift)[None]


@pytest.mark.parametrize("angle", [0.0, 17.0, 30.0, 52.0, 71.0])
def test_edge_shift_of_a_moved_straight_edge(angle):
    """A straight edge moved by 3 pixels: 3 over (|cos| + |sin|) pi / 4, the length
    factor's error at the edge's angle (exact on average over angles, at most 22%)."""
    before, after = _half_plane(0.0, angle), _half_plane(3.0, angle)
    mask = np.ones_like(before)
    got = lamp_cues.edge_shift(before, after, mask)
    a = math.radians(angle)
    assert got == pytest.approx(3.0 / ((abs(math.cos(a)) + abs(math.sin(a))) * math.pi / 4),
                                rel=0.03)
    assert got == pytest.approx(3.0, rel=0.3)
    assert math.isnan(lamp_cues.edge_shift(np.zeros_like(before), after, mask))


def test_falloff_change_takes_the_scale_out():
    rng = np.random.default_rng(0)
    before = rng.uniform(0.5, 1.0, (1, 40, 40))
    lit = np.ones_like(before, bool)
    assert lamp_cues.falloff_change(before, 3.0 * before, lit) == pytest.approx((0.0, 0.0))
    x = np.linspace(-1, 1, 40)[None, None, :] * np.ones((1, 40, 1))
    mean, p95 = lamp_cues.falloff_change(before, before * (1 + 0.02 * x), lit)
    assert mean == pytest.approx(0.01, rel=0.05) and p95 == pytest.approx(0.019, rel=0.05)


def test_moved_lamps_keep_the_distance_or_the_direction():
    center = np.array([0.1, 0.2, -0.3])
    d = np.array([0.3, 0.8, -0.2])
    d /= np.linalg.norm(d)
    lamp = Light("lamp", tuple(d), (3.0, 3.0, 3.0), 0.0, 0.0,
                 position=tuple(center + 6.0 * d), radius=0.15, distance=6.0)
    cfg = lamp_cues.CueConfig()
    moved = {m.name: m for m in lamp_cues.moved_lamps(lamp, center, cfg)}
    assert list(moved) == ["lamp", "farther", "nearer", "elevation", "azimuth"]
    for name, m in moved.items():
        off = np.asarray(m.position) - center
        dist = np.linalg.norm(off)
        assert m.radius == 0.0 and m.distance == pytest.approx(dist)
        angle = math.degrees(math.acos(np.clip(off @ d / dist, -1, 1)))
        if name in ("farther", "nearer"):
            assert dist == pytest.approx(6.0 * (1.05 if name == "farther" else 0.95))
            assert angle == pytest.approx(0.0, abs=1e-5)
        elif name != "lamp":
            assert dist == pytest.approx(6.0) and angle == pytest.approx(1.0, abs=1e-6)
    def elevation(m):
        off = np.asarray(m.position) - center
        return math.degrees(math.asin(off[1] / np.linalg.norm(off)))
    # the azimuth move keeps the elevation (to second order), the elevation move does not
    assert elevation(moved["azimuth"]) == pytest.approx(elevation(lamp), abs=0.02)
    assert abs(elevation(moved["elevation"]) - elevation(lamp)) == pytest.approx(1.0, abs=0.01)


def test_quick_study_writes_its_table_and_result(tmp_path):
    """The smoke run: the lamp's distance shows less than a degree of its direction."""
    summary = lamp_cues.run(tmp_path / "out", quick=True, quiet=True,
                            results=str(tmp_path / "results"))
    (row,) = summary["tables"]
    assert 0 < row["along"] < row["across"] and 0 < row["degrees"] < 1
    assert 0 < row["falloff_mean"] < 0.05
    doc = json.loads((tmp_path / "results" / "lamp_cues.json").read_text())
    assert doc["tables"][0]["rows"][0][:3] == ["default", "6", "1"]
    assert (tmp_path / "out" / "README.md").is_file()
