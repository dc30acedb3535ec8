"""The viewer's page in a real headless Chromium: it loads, the light's azimuth
slider is dragged, the picture changes where the shadows should move (newly lit pixels
brighten, newly shadowed ones darken: the library's own visibility says which), and a
screenshot is written.

Needs Debian's ``chromium`` and ``chromium-driver`` (``scripts/setup.sh`` installs them as
root during ``make install``) and ``selenium``; skipped with the reason where they are
missing. Chromium is started with no background networking: the machine's closed network
refuses its connections otherwise, and the page needs none (viser's client is served by
the viewer itself, on 127.0.0.1)."""

from __future__ import annotations

import shutil
import time

import numpy as np
import pytest
import view_fixtures

from mi_shadowgs.stages.viewer import viewer

pytestmark = pytest.mark.browser

CHROMIUM = shutil.which("chromium") or shutil.which("chromium-browser")
DRIVER = shutil.which("chromedriver")
try:
    import selenium  # noqa: F401
    HAVE_SELENIUM = True
except ImportError:
    HAVE_SELENIUM = False
WHY = ("needs chromium, chromium-driver (apt-get install -y chromium chromium-driver; "
       "scripts/setup.sh does it as root) and selenium (the dev extra)")
WINDOW = (1400, 800)


@pytest.fixture(scope="module")
def browser(tmp_path_factory):
    if not (CHROMIUM and DRIVER and HAVE_SELENIUM):
        pytest.skip(f"{WHY}; found chromium={CHROMIUM}, chromedriver={DRIVER}, "
                    f"selenium={HAVE_SELENIUM}")
    from selenium import webdriver
    from selenium.webdriver.chrome.service import Service

    opts = webdriver.ChromeOptions()
    opts.binary_location = CHROMIUM
    profile = tmp_path_factory.mktemp("view-chromium")
    for arg in ("--headless", "--no-sandbox", "--disable-gpu", "--disable-quic",
                "--no-first-run", "--disable-background-networking",
                "--disable-component-update", "--disable-sync",
                f"--user-data-dir={profile}", f"--window-size={WINDOW[0]},{WINDOW[1]}"):
        opts.add_argument(arg)
    driver = webdriver.Chrome(service=Service(DRIVER), options=opts)
    try:
        yield driver
    finally:
        driver.quit()


@pytest.fixture(scope="module")
def server(tmp_path_factory):
    from mi_shadowgs.stages.viewer import server as viewer_server

    run, _ = view_fixtures.make_run(tmp_path_factory.mktemp("view_browser"))
    session = viewer.ViewerSession(run)
    start = [viewer.DirectionalLight(60.0, 35.0, 3.0)]
    srv = viewer_server.ViewerServer(session, port=0, resolution=128, settle_s=0.2,
                                     initial_lights=start).start()
    try:
        yield srv
    finally:
        srv.stop()


def _wait_full_frame(srv, after: int = 0, timeout: float = 60.0):
    """The tab's first full-size frame after its ``after``-th frame."""
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        shown = next(iter(srv.shown.values()), None)
        if shown is not None and shown.count > after and not shown.preview:
            time.sleep(1.0)  # a later frame (the arrows' redraw) may still be on its way
            again = next(iter(srv.shown.values()))
            if again.count == shown.count:
                return shown
        time.sleep(0.1)
    raise AssertionError(f"no full frame within {timeout} s; errors: {srv.errors}")


def _row(driver, label: str):
    """The GUI row whose label reads ``label``."""
    from selenium.webdriver.common.by import By

    return driver.find_element(By.XPATH, f"(//label[normalize-space()='{label}'])[1]/"
                                         "ancestor::div[contains(@class,'mantine-Flex-root')][1]")


def _canvas_image(driver, shown) -> np.ndarray:
    """The page's 3D canvas as RGB [h, w, 3] at the frame's size (nearest pixel)."""
    import imageio.v3 as iio
    from selenium.webdriver.common.by import By

    canvas = driver.find_elements(By.TAG_NAME, "canvas")[0]
    img = iio.imread(canvas.screenshot_as_png, extension=".png")[..., :3]
    h, w = shown.camera.height, shown.camera.width
    ys = ((np.arange(h) + 0.5) * img.shape[0] / h).astype(int)
    xs = ((np.arange(w) + 0.5) * img.shape[1] / w).astype(int)
    return img[ys][:, xs].astype(np.float64), canvas.size


def test_dragging_the_light_slider_moves_the_shadows(browser, server, tmp_path):
    from selenium.webdriver.common.action_chains import ActionChains
    from selenium.webdriver.common.by import By

    browser.get(server.url)
    _wait_full_frame(server)
    # Arrows off: they move with the light and would hide the change under them.
    for label in ("new lights (arrows)", "fitted lights (arrows)"):
        _row(browser, label).find_element(By.CSS_SELECTOR, "input[type=checkbox]").click()
    deadline = time.monotonic() + 10
    while (server.show_new.value or server.show_fitted.value) and time.monotonic() < deadline:
        time.sleep(0.05)
    assert not server.show_new.value and not server.show_fitted.value
    before = _wait_full_frame(server)
    assert before.lights.directional[0].azimuth_deg == 60.0
    image_before, size = _canvas_image(browser, before)

    thumb = _row(browser, "azimuth").find_element(By.CSS_SELECTOR, "[role=slider]")
    ActionChains(browser).click_and_hold(thumb).move_by_offset(15, 0).pause(0.2) \
        .move_by_offset(15, 0).pause(0.2).move_by_offset(10, 0).release().perform()
    after = _wait_full_frame(server, before.count)
    az = after.lights.directional[0].azimuth_deg
    assert az == server.lights[0][1].value and az >= 90.0  # ~3 degrees a pixel
    assert after.count > before.count
    image_after, _ = _canvas_image(browser, after)
    shot = tmp_path / "view_after_drag.png"
    assert browser.save_screenshot(str(shot)) and shot.stat().st_size > 10_000

    # Where the library says the shadow left or arrived, for the camera the page used.
    assert after.camera.c2w.tobytes() == before.camera.c2w.tobytes()
    s = server.session
    va = s.render(before.camera, before.lights, visibility=True).visibility[..., 0]
    vb = s.render(after.camera, after.lights, visibility=True).visibility[..., 0]
    covered = before.frame.alpha > 0.99
    # Away from overlays: the GUI panel (right) and viser's notices (top left).
    h, w = covered.shape
    ys, xs = np.mgrid[0:h, 0:w]
    free = (xs < w * (1 - 380 / size["width"])) & ~((xs < w * 340 / size["width"]) &
                                                      (ys < h * 170 / size["height"]))
    lum_b, lum_a = image_before.mean(-1), image_after.mean(-1)
    now_lit = covered & free & (va == 0) & (vb == 1)
    now_dark = covered & free & (va == 1) & (vb == 0)
    same = covered & free & (va == vb)
    assert now_lit.sum() > 30 and now_dark.sum() > 30, (now_lit.sum(), now_dark.sum())
    lit_gain = np.median(lum_a[now_lit] - lum_b[now_lit])
    dark_gain = np.median(lum_a[now_dark] - lum_b[now_dark])
    assert lit_gain > 20 and dark_gain < -20, (lit_gain, dark_gain)
    # The shadows' move stands out from the shading change elsewhere.
    assert abs(lit_gain) > 2 * np.median(np.abs(lum_a[same] - lum_b[same]))
