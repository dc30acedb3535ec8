"""The splat PLYs in the splat tools themselves: PlayCanvas's ``splat-transform`` (npm
``@playcanvas/splat-transform``) reads our export and writes it back (dropping our header
comments), which our reader reads back right with ``SPLAT_TOOLS``; and its SuperSplat viewer
page, in headless Chromium with WebGL on the CPU (SwiftShader), shows the export upright
from its default camera.

Needs node with ``splat-transform`` (``npm install -g @playcanvas/splat-transform``, or the
path of its CLI in ``SPLAT_TRANSFORM``); skipped with the reason where it is missing.
Nothing is installed here.
"""

from __future__ import annotations

import os
import shutil
import subprocess
import time
from pathlib import Path

import numpy as np
import pytest

from mi_shadowgs import cli
from mi_shadowgs.io import ply
from tests import synthetic_asset as syn

_LOCAL = Path(__file__).resolve().parents[1] / ".venv/node/node_modules/.bin/splat-transform"
SPLAT_TRANSFORM = (os.environ.get("SPLAT_TRANSFORM") or shutil.which("splat-transform")
                   or (str(_LOCAL) if _LOCAL.is_file() else None))
NO_SPLAT = ("needs node and PlayCanvas's splat-transform (apt-get install -y nodejs npm; "
            "npm install -g @playcanvas/splat-transform, or SPLAT_TRANSFORM=path/to/its "
            "cli); not found")
pytestmark = pytest.mark.skipif(SPLAT_TRANSFORM is None, reason=NO_SPLAT)


@pytest.fixture(scope="module")
def exported(tmp_path_factory):
    root = tmp_path_factory.mktemp("splat")
    run, _ = syn.fake_run(root)
    out = root / "export"
    assert cli.main(["export", str(run), "--format", "3dgs-ply", "--out", str(out),
                     "--no-progress"]) == 0
    return run, out / "point_cloud.ply"


def _splat_transform(*args, timeout=300) -> subprocess.CompletedProcess:
    res = subprocess.run([SPLAT_TRANSFORM, "-w", *map(str, args)], capture_output=True,
                         text=True, timeout=timeout)
    assert res.returncode == 0, res.stdout + res.stderr
    return res


def test_a_round_trip_through_splat_transform_reads_back_with_one_flag(exported, tmp_path):
    run, path = exported
    ours = ply.read_ply_model(run / "material" / "full" / "model.ply")
    assert ply.read_ply_model(path).position.tobytes() == ours.position.tobytes()
    _splat_transform(path, tmp_path / "back.ply")
    assert ply.read_ply_metadata(tmp_path / "back.ply") == {}  # the comments are gone
    back = ply.read_ply_model(tmp_path / "back.ply", **ply.SPLAT_TOOLS)
    order = np.lexsort(back.position.T)  # the tool may reorder the splats
    ref = np.lexsort(ours.position.T)
    np.testing.assert_allclose(back.position[order], ours.position[ref], atol=1e-6)
    q = back.rotation[order] / np.linalg.norm(back.rotation[order], axis=1, keepdims=True)
    r = ours.rotation[ref] / np.linalg.norm(ours.rotation[ref], axis=1, keepdims=True)
    assert np.abs(np.abs(np.sum(q * r, axis=1)) - 1).max() < 1e-5  # the same rotations
    k = ours.channels["sh"].shape[1]
    np.testing.assert_allclose(back.channels["sh"][order, :k], ours.channels["sh"][ref],
                               atol=2e-4)


CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
DRIVER = shutil.which("chromedriver")
# SwiftShader: WebGL2 on the CPU, for a machine without a GPU.
WEBGL_ON_CPU = ("--use-gl=angle", "--use-angle=swiftshader", "--enable-unsafe-swiftshader",
                "--ignore-gpu-blocklist")


def _viewer_html(ply_path, html) -> None:
    """splat-transform's SuperSplat viewer page of ``ply_path``, without the SH bands above
    the colour (``-H 0``: their compression takes minutes on a CPU and the frame is the
    positions' and rotations'), ``-g cpu``: no GPU."""
    _splat_transform("-g", "cpu", ply_path, "-H", "0", html)


def _screenshot(driver, page, shot, wait_s: float = 120.0) -> np.ndarray:
    """The page's screenshot [H, W, 3] once the viewer has drawn: not one flat colour (the
    loader), and the picture's contrast as in the screenshot before (the splats sorted and
    drawn; SwiftShader's frames differ by noise, so the pixels themselves never settle)."""
    from mi_shadowgs.io.images import read_png

    driver.get(page.as_uri())
    t0, last = time.monotonic(), None
    while time.monotonic() - t0 < wait_s:
        time.sleep(1.0)
        driver.save_screenshot(str(shot))
        img = read_png(shot)[..., :3].astype(np.float64)
        if last is not None and img.std() > 5 and abs(img.std() - last.std()) < 0.5:
            return img
        last = img
    raise AssertionError(f"{page}: the viewer drew nothing steady in {wait_s:.0f} s ({shot})")


def _upright(img: np.ndarray) -> tuple[bool, str]:
    """(whether the sphere stands upright on its plate, what was seen): the sphere's red
    upper half (``synthetic_asset.TOP_ALBEDO``) above its blue lower half, and the sphere
    above the middle of the grey plate, in image rows weighted by how strongly each pixel
    has that colour."""
    r, g, b = img[..., 0], img[..., 1], img[..., 2]
    rows = np.arange(img.shape[0])[:, None] * np.ones(img.shape[1])
    red = np.clip(r - np.maximum(g, b) - 30, 0, None)
    blue = np.clip(b - np.maximum(r, g) - 30, 0, None)
    grey = ((np.abs(r - g) < 8) & (np.abs(g - b) < 8) & (g > 150)).astype(np.float64)
    if red.sum() == 0 or blue.sum() == 0 or grey.sum() == 0:
        return False, (f"red {red.sum():.0f}, blue {blue.sum():.0f}, plate {grey.sum():.0f} "
                       "(sphere or plate hidden)")
    row = {k: float((rows * m).sum() / m.sum()) for k, m in
           (("red", red), ("blue", blue), ("plate", grey))}
    seen = ", ".join(f"{k} at row {v:.0f}" for k, v in row.items())
    return row["red"] < row["blue"] < row["plate"], seen


@pytest.mark.browser
@pytest.mark.skipif(not (CHROMIUM and DRIVER), reason="needs chromium and chromium-driver "
                    "(apt-get install -y chromium chromium-driver; scripts/setup.sh "
                    "--chromium) and selenium (the dev extra)")
def test_supersplat_shows_the_export_upright(exported, tmp_path):
    """SuperSplat's viewer (splat-transform's HTML page) from its default camera: the
    sphere's red upper half above its blue lower half. The same model exported in our
    frame (``--frame y-up``, which SuperSplat takes for Y down) is the flipped reference:
    its sphere hangs below the plate, out of sight from the default camera above, and the
    check tells the two apart."""
    pytest.importorskip("selenium", reason="needs selenium (the dev extra)")
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    run, path = exported
    flipped = tmp_path / "flipped"
    assert cli.main(["export", str(run), "--format", "3dgs-ply", "--frame", "y-up", "--out",
                     str(flipped), "--no-progress"]) == 0
    _viewer_html(path, tmp_path / "upright.html")
    _viewer_html(flipped / "point_cloud.ply", tmp_path / "flipped.html")
    opts = webdriver.ChromeOptions()
    opts.binary_location = CHROMIUM
    for arg in ("--headless=new", "--no-sandbox", "--disable-dev-shm-usage",
                "--disable-background-networking", "--window-size=800,600",
                f"--user-data-dir={tmp_path / 'profile'}", *WEBGL_ON_CPU):
        opts.add_argument(arg)
    driver = webdriver.Chrome(service=Service(DRIVER), options=opts)
    try:
        up = _upright(_screenshot(driver, tmp_path / "upright.html", tmp_path / "upright.png"))
        down = _upright(_screenshot(driver, tmp_path / "flipped.html",
                                    tmp_path / "flipped.png"))
    finally:
        driver.quit()
    assert up[0], f"the export is not upright in SuperSplat: {up[1]} ({tmp_path})"
    assert not down[0], f"the flipped reference reads as upright: {down[1]} ({tmp_path})"
