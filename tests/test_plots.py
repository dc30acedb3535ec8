"""The report's plots are drawn once per input: a PNG holding the digest of the same
inputs is kept, anything else at its path is drawn again."""

from __future__ import annotations

import numpy as np

from mi_shadowgs.io import plots


def _panels(y_last: float) -> list[dict]:
    return [{"ylabel": "loss", "log": True,
             "lines": [{"x": [0, 10, 20], "y": np.array([1.0, 0.5, y_last])}]}]


def _counting(monkeypatch) -> list[int]:
    drawn = []
    real = plots._figure
    monkeypatch.setattr(plots, "_figure", lambda *a: (drawn.append(1), real(*a))[1])
    return drawn


def test_a_plot_of_the_same_inputs_is_not_drawn_again(tmp_path, monkeypatch):
    drawn = _counting(monkeypatch)
    path = tmp_path / "curves.png"
    plots.curves_png(path, _panels(0.25), title="t", markers=[{"x": 10, "label": "m"}])
    first = path.read_bytes()
    assert len(drawn) == 1 and plots.INPUTS_KEY in plots.png_text(path)
    plots.curves_png(path, _panels(0.25), title="t", markers=[{"x": 10, "label": "m"}])
    assert len(drawn) == 1 and path.read_bytes() == first
    # Into a new folder beside the earlier one (a run's report is made in a temporary
    # folder): copied from there.
    (tmp_path / "new").mkdir()
    plots.curves_png(tmp_path / "new" / "curves.png", _panels(0.25), title="t",
                     markers=[{"x": 10, "label": "m"}], earlier=tmp_path)
    assert len(drawn) == 1 and (tmp_path / "new" / "curves.png").read_bytes() == first
    # One value, a title or a marker changed: drawn again, with another digest.
    for kwargs in ({"panels": _panels(0.3), "title": "t"}, {"panels": _panels(0.25)},
                   {"panels": _panels(0.25), "title": "t", "markers": [{"x": 11,
                                                                        "label": "m"}]}):
        before = plots.png_text(path)[plots.INPUTS_KEY]
        plots.curves_png(path, **kwargs)
        assert plots.png_text(path)[plots.INPUTS_KEY] != before, kwargs
    assert len(drawn) == 4


def test_a_file_not_drawn_from_these_inputs_is_replaced(tmp_path, monkeypatch):
    drawn = _counting(monkeypatch)
    a, b = tmp_path / "a.png", tmp_path / "b.png"
    plots.colorbar_png(a)
    plots.colorbar_png(b, vmax=0.5)
    b.write_bytes(a.read_bytes())  # another plot's PNG under this name
    plots.colorbar_png(b, vmax=0.5)
    assert len(drawn) == 3 and b.read_bytes() != a.read_bytes()
    for junk in (b"not a png", b""):  # a user's file, a cut write
        b.write_bytes(junk)
        plots.colorbar_png(b, vmax=0.5)
        assert plots.png_text(b)[plots.INPUTS_KEY]
    assert len(drawn) == 5
    assert plots.png_text(tmp_path / "missing.png") == {}
