"""The report's plots (matplotlib, Agg backend), written as deterministic PNGs.

Every figure is byte-identical across runs given the same data: the PNG carries no
'Software' or date text, the size and DPI are fixed, and no figure state is shared (each
plot builds its own ``Figure``, not pyplot's global one). Run outputs are compared byte for
byte (``tests/test_kill.py``).

Each PNG holds a digest of what drew it (the plot's name and arguments, this file and
matplotlib's version) in a text chunk; a plot whose file already holds the digest of its
inputs is not drawn again (a rerun of a finished run redraws nothing).
"""

from __future__ import annotations

import functools
import hashlib
import io
import os
import struct
from importlib import metadata
from pathlib import Path
from typing import TYPE_CHECKING

import numpy as np

from mi_shadowgs.io.atomic import write_bytes

if TYPE_CHECKING:
    from matplotlib.figure import Figure

DPI = 100
ERROR_MAX = 0.25  # error maps: |estimate - ground truth| in sRGB [0, 1], colour-mapped 0..this
ERROR_CMAP = "inferno"


_MARKER_STYLES = ("--", ":", "-.")


def _figure(width_in: float, height_in: float):
    from matplotlib.figure import Figure

    return Figure(figsize=(width_in, height_in), dpi=DPI, layout="constrained")


INPUTS_KEY = "mi_shadowgs inputs"  # the PNG text chunk holding the digest of the inputs


def _feed(h, value) -> None:
    """``value`` (JSON-like, with NumPy arrays and scalars) into the hash ``h``, typed."""
    if isinstance(value, np.ndarray):
        h.update(f"a{value.dtype.str}{value.shape}".encode())
        h.update(np.ascontiguousarray(value).tobytes())
    elif isinstance(value, dict):
        h.update(f"d{len(value)}".encode())
        for k in sorted(value, key=str):
            _feed(h, str(k))
            _feed(h, value[k])
    elif isinstance(value, (list, tuple)):
        h.update(f"l{len(value)}".encode())
        for v in value:
            _feed(h, v)
    elif isinstance(value, np.generic):
        _feed(h, value.item())
    else:  # str, int, float, bool, None
        h.update(f"{type(value).__name__}:{value!r};".encode())


@functools.cache
def _code_version() -> bytes:
    return Path(__file__).read_bytes() + metadata.version("matplotlib").encode()


def _digest(name: str, args: tuple, kwargs: dict) -> str:
    h = hashlib.sha256(_code_version())
    _feed(h, [name, list(args), kwargs])
    return h.hexdigest()


def png_text(path: str | os.PathLike) -> dict[str, str]:
    """The tEXt chunks of a PNG file ({} when it is missing or not a PNG)."""
    return _text_chunks(_read(path))


def _read(path: str | os.PathLike) -> bytes:
    try:
        return Path(path).read_bytes()
    except OSError:
        return b""


def _text_chunks(data: bytes) -> dict[str, str]:
    if data[:8] != b"\x89PNG\r\n\x1a\n":
        return {}
    out, pos = {}, 8
    while pos + 8 <= len(data):
        length, kind = struct.unpack(">I4s", data[pos:pos + 8])
        if kind == b"tEXt":
            key, _, text = data[pos + 8:pos + 8 + length].partition(b"\0")
            out[key.decode("latin-1")] = text.decode("latin-1")
        if kind == b"IEND":
            break
        pos += 12 + length
    return out


def _plot(draw):
    """A plot function ``draw(path, ...)`` that returns its ``Figure``: written to ``path``
    with the digest of its inputs, and not drawn when ``path``, or the file of its name in
    the folder ``earlier`` (copied then), already holds that digest."""

    @functools.wraps(draw)
    def plot(path: str | os.PathLike, *args, earlier: Path | None = None, **kwargs) -> None:
        key = _digest(draw.__name__, args, kwargs)
        sources = [Path(path)] + ([Path(earlier) / Path(path).name] if earlier else [])
        for source in sources:
            data = _read(source)
            if _text_chunks(data).get(INPUTS_KEY) == key:
                if source != sources[0]:
                    write_bytes(path, data)
                return
        from matplotlib.backends.backend_agg import FigureCanvasAgg

        fig = draw(path, *args, **kwargs)
        FigureCanvasAgg(fig)
        buf = io.BytesIO()
        fig.savefig(buf, format="png", dpi=DPI, metadata={"Software": None, INPUTS_KEY: key})
        write_bytes(path, buf.getvalue())

    return plot


@_plot
def curves_png(path: str | os.PathLike, panels: list[dict], xlabel: str = "iteration",
               title: str | None = None, markers: list[dict] | None = None) -> Figure:
    """Side-by-side line plots. Each panel is ``{"ylabel": str, "log": bool, "lines":
    [{"x": [N], "y": [N], "label": str | None}]}``; NaNs are gaps. ``markers``
    (``[{"x", "label"}]``, where a loss term starts) are dashed vertical lines on every
    panel, named in a legend below the panels."""
    n = max(len(panels), 1)
    fig = _figure(3.4 * n, 2.8)
    axes = fig.subplots(1, n, squeeze=False)[0]
    marks = []
    for ax, p in zip(axes, panels, strict=False):
        labelled = False
        for k, line in enumerate(p["lines"]):
            ax.plot(np.asarray(line["x"], np.float64), np.asarray(line["y"], np.float64),
                    lw=1.4, color=f"C{k}", label=line.get("label"))
            labelled |= bool(line.get("label"))
        marks = [ax.axvline(m["x"], color="0.35", lw=1.0,
                            ls=_MARKER_STYLES[k % len(_MARKER_STYLES)])
                 for k, m in enumerate(markers or [])]
        ys = np.concatenate([np.asarray(ln["y"], np.float64).ravel() for ln in p["lines"]]
                            or [np.zeros(0)])
        if p.get("log") and np.any(ys > 0):
            ax.set_yscale("log")
        if labelled:
            ax.legend(fontsize=7.5)
        ax.set_xlabel(xlabel)
        ax.set_ylabel(p["ylabel"])
        ax.grid(alpha=0.3)
    if markers:
        fig.legend(marks, [m["label"] for m in markers], loc="outside lower center",
                   ncol=len(markers), fontsize=7.5, frameon=False)
    if title:
        fig.suptitle(title, fontsize=11)
    return fig


@_plot
def light_map_png(path: str | os.PathLike, est_blocks: np.ndarray, gt_blocks: np.ndarray | None,
                  gt_lights: list[dict], fitted: list[dict],
                  grid: np.ndarray | None = None) -> Figure:
    """The paper's 22 x 12 light map, estimate and ground truth side by side.

    ``est_blocks``/``gt_blocks`` [12, 22]: rows from the zenith down to the horizon, columns
    over azimuth [0, 360) (``core.directions.map_to_blocks``), each normalised to its peak.
    ``gt_lights``: ``{"azimuth", "elevation", "label"}`` (degrees) marked as rings on both,
    with optional ``"grid_azimuth"``/``"grid_elevation"``: the grid direction the map puts
    the light on, marked "+" and joined to its ring; ``fitted``: ``{"azimuth", "elevation",
    "weight"}`` marked as crosses (size by weight) on the estimate; ``grid`` [N, 2]: the
    azimuth and elevation of the light grid's directions, small dots on both.
    """
    maps = [("estimate", est_blocks)] + ([("ground truth", gt_blocks)]
                                         if gt_blocks is not None else [])
    fig = _figure(5.2 * len(maps) + 0.6, 2.9)
    axes = fig.subplots(1, len(maps), squeeze=False)[0]
    im = None
    for ax, (name, blocks) in zip(axes, maps, strict=True):
        b = np.asarray(blocks, np.float64)
        peak = b.max() if b.size else 0.0
        im = ax.imshow(b / peak if peak > 0 else b, extent=(0, 360, 0, 90), origin="upper",
                       cmap="magma", vmin=0.0, vmax=1.0, aspect="auto",
                       interpolation="nearest")
        ax.set_title(name, fontsize=10)
        ax.set_xlabel("azimuth (deg)")
        ax.set_ylabel("elevation (deg)")
        ax.set_xticks(range(0, 361, 60))
        ax.set_yticks(range(0, 91, 30))
        if grid is not None and len(grid):
            ax.plot(grid[:, 0], grid[:, 1], ".", ms=2.5, color="0.55",
                    label=f"the {len(grid)} grid directions")
        snapped = False
        for lt in gt_lights:
            ax.plot(lt["azimuth"], lt["elevation"], "o", ms=11, mfc="none", mec="#19d3ff",
                    mew=1.8, label=lt["label"])
            if "grid_azimuth" in lt and abs(lt["grid_azimuth"] - lt["azimuth"]) < 180:
                ax.plot([lt["azimuth"], lt["grid_azimuth"]],
                        [lt["elevation"], lt["grid_elevation"]], "-", color="#19d3ff", lw=0.8)
                ax.plot(lt["grid_azimuth"], lt["grid_elevation"], "+", ms=9, mew=1.8,
                        color="#19d3ff", label=None if snapped else
                        "a true light's nearest grid direction (its block in the maps)")
                snapped = True
        if name == "estimate" and fitted:
            w = np.asarray([f["weight"] for f in fitted], np.float64)
            w = w / w.max() if w.max() > 0 else np.ones_like(w)
            ax.scatter([f["azimuth"] for f in fitted], [f["elevation"] for f in fitted],
                       s=10 + 70 * w, marker="x", c="#7CFC00", linewidths=1.2,
                       label="fitted lights")
        ax.set_xlim(0, 360)
        ax.set_ylim(0, 90)
    if gt_lights or fitted:
        axes[0].legend(loc="upper center", bbox_to_anchor=(0.5, -0.28), fontsize=7.5,
                       ncol=2, frameon=False)
    fig.colorbar(im, ax=list(axes), label="radiance / peak", shrink=0.9)
    return fig


def error_colors(est: np.ndarray, gt: np.ndarray, vmax: float = ERROR_MAX) -> np.ndarray:
    """Colour-mapped |est - gt| (mean over channels) [H, W, 3] in [0, 1], for display images
    ([H, W] or [H, W, 3], same space) mapped 0..``vmax`` through ``ERROR_CMAP``."""
    from matplotlib import colormaps

    e = np.abs(np.asarray(est, np.float64) - np.asarray(gt, np.float64))
    if e.ndim == 3:
        e = e.mean(-1)
    return colormaps[ERROR_CMAP](np.clip(e / vmax, 0.0, 1.0))[..., :3]


@_plot
def colorbar_png(path: str | os.PathLike, vmax: float = ERROR_MAX,
                 label: str = "|estimate - ground truth| (sRGB)") -> Figure:
    """A horizontal colour bar for ``error_colors``."""
    import matplotlib as mpl

    fig = _figure(3.6, 0.75)
    ax = fig.add_subplot()
    fig.colorbar(mpl.cm.ScalarMappable(mpl.colors.Normalize(0.0, vmax), ERROR_CMAP), cax=ax,
                 orientation="horizontal", label=label)
    return fig

