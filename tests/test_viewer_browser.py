"""``kpcn view``'s page in a real browser (headless Chromium, driven by Selenium): it loads, the four views are
there (OIDN's enabled exactly where ``pyoidn`` is installed), a pixel on the canvas is the view through the
display transform of ``prep.colour.tonemap`` after the exposure, and a brush stroke scripted with the mouse
changes the denoised pixels under it and none far from it, on the server and on the screen; with a pair, a click
on *adapt* adapts in the background and shows the adapted view beside kpcn's, drawn as the server's."""

import json
import threading
import urllib.request

import numpy as np
import pytest
from helpers.browser import headless_chromium
from helpers.networks import randomise
from helpers.tiny import random_aovs

from kpcn_keras.batch import read_frame
from kpcn_keras.denoise import Denoiser
from kpcn_keras.run import Run
from kpcn_keras.settings import InferenceSettings
from kpcn_keras.studies.browser import page_input, page_stroke, page_wait
from kpcn_keras.viewer import VIEWS, ViewSession, listen
from prep import baselines, exr
from prep.colour import tonemap

pytestmark = pytest.mark.slow  # a browser start

H, W = 48, 64
RADIUS = 4  # the brush, in image pixels
PATH = ((20.5, 24.5), (28.5, 22.5), (40.5, 24.5))  # the stroke, image coordinates


@pytest.fixture
def page(tmp_path, tiny_slope_module_run):
    exr.write_aovs(tmp_path / "frame.exr", random_aovs(H, W, seed=21))
    exr.write_aovs(tmp_path / "reference.exr", random_aovs(H, W, seed=22, variances=False))
    # weights far from the trained few steps' (whose zero-initialised head has barely moved), so that λ shows
    den = Denoiser.from_run(Run(tiny_slope_module_run), InferenceSettings(precision="float32"))
    for i, model in enumerate(den.networks.values()):
        randomise(model, seed=40 + i)
    reference = exr.read_aovs(tmp_path / "reference.exr", variances=False)["default"]
    session = ViewSession(read_frame(tmp_path / "frame.exr"), den, reference, slope=1.0, log=lambda m: None)
    httpd = listen(0)
    httpd.session = session
    threading.Thread(target=httpd.serve_forever, daemon=True).start()
    url = f"http://127.0.0.1:{httpd.server_address[1]}/"
    try:
        with headless_chromium(tmp_path / "profile") as driver:
            driver.get(url)
            page_wait(driver, "window.kpcn && window.kpcn.ready")
            yield driver, url
    finally:
        httpd.shutdown()
        httpd.server_close()


def denoised(url: str) -> np.ndarray:
    with urllib.request.urlopen(f"{url}api/view/denoised", timeout=60) as res:
        return np.frombuffer(res.read(), "<f4").reshape(H, W, 3).copy()


def canvas_pixels(driver, points) -> np.ndarray:
    """The canvas's RGB bytes at the centres of image pixels ``points`` (x, y)."""
    return np.array(driver.execute_script(
        "const s = kpcn.state, c = document.getElementById('canvas').getContext('2d');"
        "return arguments[0].map(([x, y]) => Array.from(c.getImageData("
        "Math.floor(s.ox + (x + 0.5) * s.zoom), Math.floor(s.oy + (y + 0.5) * s.zoom), 1, 1).data.slice(0, 3)));",
        [list(p) for p in points]))


def test_the_page_loads_with_the_four_views_and_draws_them_through_the_display_transform(page):
    driver, url = page
    options = driver.execute_script("return Array.from(document.getElementById('left').options).map("
                                    "o => [o.value, o.disabled])")
    assert [name for name, _ in options] == [*(v for v in VIEWS if v != "adapted"), "lambda"]  # no pair: no adapting
    assert driver.execute_script("return document.getElementById('adapt-run').disabled")
    assert dict(options)["oidn"] is not baselines.oidn_available()
    assert not any(disabled for name, disabled in options if name != "oidn")
    for side in ("left", "right"):
        page_input(driver, side, "denoised")
    page_input(driver, "exposure", 1.5)
    points = [(5, 7), (33, 20), (60, 44)]
    got = canvas_pixels(driver, points)
    view = denoised(url)
    want = np.round(255 * tonemap(np.stack([view[y, x] for x, y in points]) * 2**1.5))
    np.testing.assert_allclose(got, want, atol=1)
    page_input(driver, "right", "reference")  # the swipe: the right half shows the reference
    page_input(driver, "split", 0.0)
    assert not np.array_equal(canvas_pixels(driver, points), got)


def test_a_scripted_brush_stroke_changes_the_denoised_pixels_under_it_and_none_far_from_it(page, tmp_path):
    driver, url = page
    for side in ("left", "right"):
        page_input(driver, side, "denoised")
    before = denoised(url)
    under = [(int(x), int(y)) for x, y in PATH]
    far = [(2, 2), (60, 45), (10, 40), (50, 5)]
    shown = canvas_pixels(driver, under + far)
    driver.find_element("css selector", "input[name=mode][value=paint]").click()
    page_input(driver, "brush-radius", RADIUS)
    page_input(driver, "brush-slope", 1)  # the top of the range: λ = 8, from 1 everywhere
    page_stroke(driver, PATH)
    page_wait(driver, "kpcn.state.strokes === 1 && !kpcn.busy()")

    after = denoised(url)
    changed = np.abs(after - before).max(axis=2) > 0
    ys, xs = np.nonzero(changed)
    assert changed.any(), "the stroke changed nothing"
    lo_x, hi_x = min(x for x, _ in PATH) - RADIUS - 1, max(x for x, _ in PATH) + RADIUS + 1
    lo_y, hi_y = min(y for _, y in PATH) - RADIUS - 1, max(y for _, y in PATH) + RADIUS + 1
    assert lo_x <= xs.min() and xs.max() <= hi_x and lo_y <= ys.min() and ys.max() <= hi_y, (xs, ys)
    assert all(changed[y, x] for x, y in under)
    y0, y1, x0, x1 = driver.execute_script("return kpcn.state.lastStroke.rect")
    assert y0 <= ys.min() and ys.max() < y1 and x0 <= xs.min() and xs.max() < x1
    now = canvas_pixels(driver, under + far)  # the screen shows the new values under the stroke, the old far off
    np.testing.assert_allclose(now[: len(under)], np.round(255 * tonemap(np.stack([after[y, x] for x, y in under]))),
                               atol=1)
    assert not np.array_equal(now[: len(under)], shown[: len(under)])
    np.testing.assert_array_equal(now[len(under):], shown[len(under):])
    assert "λ re-applied" in driver.find_element("id", "status").text
    driver.save_screenshot(str(tmp_path / "view.png"))
    from PIL import Image

    with Image.open(tmp_path / "view.png") as shot:
        assert list(shot.size) == driver.execute_script("return [window.innerWidth, window.innerHeight]")


def test_a_click_on_adapt_adapts_in_the_background_and_shows_the_adapted_view_beside_kpcns(tmp_path, tiny_run):
    from helpers.halves import write_halves

    from kpcn_keras.batch import ReadOptions

    a, b = write_halves(tmp_path, H, W, seed=9)
    session = ViewSession.open(a, Run(tiny_run), reading=ReadOptions(pair=b),
                               settings=InferenceSettings(precision="float32"), log=lambda m: None)
    httpd = listen(0)
    httpd.session = session
    threading.Thread(target=httpd.serve_forever, daemon=True).start()
    url = f"http://127.0.0.1:{httpd.server_address[1]}/"
    try:
        with headless_chromium(tmp_path / "profile") as driver:
            driver.get(url)
            page_wait(driver, "window.kpcn && window.kpcn.ready")
            disabled = driver.execute_script("return Array.from(document.getElementById('right').options).map("
                                             "o => [o.value, o.disabled])")
            assert dict(disabled)["adapted"]  # nothing to show before adapting
            page_input(driver, "adapt-seconds", 2)
            driver.find_element("id", "adapt-run").click()
            page_wait(driver, "kpcn.state.adaptations === 1 && !kpcn.busy()", timeout=120)
            with urllib.request.urlopen(f"{url}api/view/adapted", timeout=60) as res:
                adapted = np.frombuffer(res.read(), "<f4").reshape(H, W, 3)
            with urllib.request.urlopen(f"{url}api/adapt", timeout=60) as res:
                line = json.loads(res.read())["outcome"]["line"]
            assert driver.execute_script("return [kpcn.state.left, kpcn.state.right]") == ["denoised", "adapted"]
            page_input(driver, "split", 0.0)  # the right view everywhere: the adapted one
            points = [(5, 7), (33, 20), (60, 44)]
            np.testing.assert_allclose(canvas_pixels(driver, points),
                                       np.round(255 * tonemap(np.stack([adapted[y, x] for x, y in points]))), atol=1)
            assert line in driver.find_element("id", "status").text
    finally:
        httpd.shutdown()
        httpd.server_close()
        assert session.close(30.0)
