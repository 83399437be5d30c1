"""Headless Chromium for the tests of ``kpcn view``'s page: the lab's driver (``kpcn_keras.studies.browser``,
which the page's screenshot study also drives), with a missing browser skipping the test rather than failing it,
except where :data:`REQUIRE_BROWSER` is set (CI sets it: there the browser must be installed)."""

import contextlib
import os
from pathlib import Path

import pytest

from kpcn_keras.studies import browser

REQUIRE_BROWSER = "KPCN_REQUIRE_BROWSER"


@contextlib.contextmanager
def headless_chromium(profile: Path, size=(1280, 800)):
    """The lab's :func:`kpcn_keras.studies.browser.headless_chromium`; the test skipped (or, under
    :data:`REQUIRE_BROWSER`, failed) with its line where Chromium or Selenium is missing."""
    missing = browser.browser_missing()
    if missing:
        if os.environ.get(REQUIRE_BROWSER):
            pytest.fail(missing)
        pytest.skip(missing)
    with browser.headless_chromium(profile, size) as driver:
        yield driver
