"""Headless Chromium driving ``kpcn view``'s page (``kpcn_keras/view/view.js``) through Selenium: the driver,
and a user's input to the page (a control set, a mouse stroke) and waits on it."""

import contextlib
import os
from pathlib import Path

import pytest

# Debian's Chromium and its driver (.ci/run installs them); the flags keep it from reaching for Google's hosts,
# which a closed network refuses many times a start
CHROMIUM, CHROMEDRIVER = Path("/usr/bin/chromium"), Path("/usr/bin/chromedriver")
CHROMIUM_FLAGS = ("--headless=new", "--no-sandbox", "--disable-gpu", "--disable-quic", "--no-first-run",
                  "--disable-background-networking", "--disable-component-update", "--disable-sync",
                  "--disable-dev-shm-usage", "--hide-scrollbars", "--force-device-scale-factor=1")
REQUIRE_BROWSER = "KPCN_REQUIRE_BROWSER"  # set (CI sets it): a missing browser fails the browser tests


@contextlib.contextmanager
def headless_chromium(profile: Path, size=(1280, 800)):
    """A Selenium driver of headless Chromium with an empty profile in ``profile``, the window ``size``; the
    test is skipped where Chromium or Selenium is missing, unless :data:`REQUIRE_BROWSER` is set."""
    try:
        from selenium import webdriver
        from selenium.webdriver.chrome.service import Service
    except ImportError:
        selenium = None
    else:
        selenium = webdriver
    missing = [what for what, here in (("selenium", selenium is not None), (str(CHROMIUM), CHROMIUM.exists()),
                                        (str(CHROMEDRIVER), CHROMEDRIVER.exists())) if not here]
    if missing:
        message = f"no browser to test the page in: {', '.join(missing)} missing (apt-get install chromium " \
                  "chromium-driver; pip install '.[test]')"
        if os.environ.get(REQUIRE_BROWSER):
            pytest.fail(message)
        pytest.skip(message)
    os.environ.setdefault("SE_OFFLINE", "true")  # Selenium Manager must not look for drivers on the network
    options = webdriver.ChromeOptions()
    options.binary_location = str(CHROMIUM)
    for flag in (*CHROMIUM_FLAGS, f"--window-size={size[0]},{size[1]}", f"--user-data-dir={profile}"):
        options.add_argument(flag)
    driver = webdriver.Chrome(service=Service(str(CHROMEDRIVER)), options=options)
    try:
        yield driver
    finally:
        driver.quit()


# driving kpcn view's page (kpcn_keras/view/view.js): its test (the lab has its own copy: kpcn_keras/studies/browser.py)


def page_wait(driver, condition: str, timeout: float = 60) -> None:
    """Wait until the page's JavaScript ``condition`` holds."""
    from selenium.webdriver.support.ui import WebDriverWait

    WebDriverWait(driver, timeout).until(lambda d: d.execute_script(f"return Boolean({condition})"))


def page_input(driver, element_id: str, value) -> None:
    """Set a control of the page (a slider or a menu) as a user does: its value, then its input or change event."""
    driver.execute_script("const e = document.getElementById(arguments[0]); e.value = arguments[1]; "
                          "e.dispatchEvent(new Event(e.tagName === 'SELECT' ? 'change' : 'input'));",
                          element_id, str(value))


def page_point(driver, x: float, y: float) -> tuple[int, int]:
    """The viewport position (CSS pixels, rounded; the device scale is 1) of image point (x, y)."""
    return tuple(round(v) for v in driver.execute_script(
        "const s = kpcn.state, r = document.getElementById('canvas').getBoundingClientRect();"
        "return [r.left + s.ox + arguments[0] * s.zoom, r.top + s.oy + arguments[1] * s.zoom];", x, y))


def page_stroke(driver, points) -> None:
    """One stroke of the mouse through the image points ``points`` (x, y): down at the first, up at the last."""
    from selenium.webdriver.common.action_chains import ActionChains
    from selenium.webdriver.common.actions.action_builder import ActionBuilder
    from selenium.webdriver.common.actions.mouse_button import MouseButton

    builder = ActionBuilder(driver)
    builder.pointer_action.move_to_location(*page_point(driver, *points[0]))
    builder.pointer_action.pointer_down(MouseButton.LEFT)
    for point in points[1:]:
        builder.pointer_action.move_to_location(*page_point(driver, *point))
    builder.pointer_action.pointer_up(MouseButton.LEFT)
    builder.perform()
    ActionChains(driver).reset_actions()
