"""The browser: Playwright driving Debian's Chromium, for the pages served by a real server."""

from __future__ import annotations

import shutil
from collections.abc import Iterator

import pytest
from playwright.sync_api import Browser, Playwright, sync_playwright


@pytest.fixture(scope="module")
def playwright() -> Iterator[Playwright]:
    """Playwright, for the browser tests (its own browser download is not reachable offline)."""
    with sync_playwright() as driver:
        yield driver


@pytest.fixture(scope="module")
def browser(playwright: Playwright) -> Iterator[Browser]:
    """Debian's Chromium, headless."""
    chromium = shutil.which("chromium")
    assert chromium, "Debian's chromium is not installed: apt-get install chromium (.ci/run does)"
    browser = playwright.chromium.launch(executable_path=chromium, headless=True)
    yield browser
    browser.close()
