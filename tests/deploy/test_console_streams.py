"""The console on a camera stream, in a real Chromium: after 300 frames of one static scene it says
"no alarm" on one independent look; after heavily occluded scenes, "alarm raised", with the looks
and frames the drift API reports (tests/live/test_drift_streams.py sends the same stream)."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest
from playwright.sync_api import Browser, BrowserContext

from tests.deploy.test_api_pages import Watch, open_page, watched_context
from tests.live.server import LiveServer
from tests.live.test_drift_streams import send_heavy_until_alarm, send_static_scene
from tests.service_calls import ADMIN_TOKEN

pytestmark = pytest.mark.browser


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[LiveServer]:
    with LiveServer(tmp_path_factory.mktemp("console-streams") / "data", admin_token=ADMIN_TOKEN) as live:
        yield live


@pytest.fixture
def context(browser: Browser, server: LiveServer) -> Iterator[tuple[BrowserContext, Watch]]:
    yield from watched_context(browser, server, {"width": 1400, "height": 1000})


def _drift_line(context: tuple[BrowserContext, Watch], server: LiveServer) -> str:
    page, watch = open_page(context, f"{server.url}/console")
    page.wait_for_selector("#model table")
    page.fill("#token", server.admin_token)
    page.click("#token-form button[type=submit]")
    page.wait_for_selector("body[data-loaded=true]")
    text = page.inner_text("#drift p.muted")
    watch.assert_offline_and_clean(page)
    page.close()
    return text


def test_the_console_shows_a_quiet_static_scene_then_the_alarm(
    server: LiveServer, context: tuple[BrowserContext, Watch], tmp_path: Path
) -> None:
    quiet = send_static_scene(server)
    line = _drift_line(context, server)
    assert f"{quiet['independent_looks']} independent looks in {quiet['frames']} frames" in line, line
    assert "no alarm" in line and "alarm raised" not in line

    _, shifted = send_heavy_until_alarm(server)
    line = _drift_line(context, server)
    assert f"{shifted['independent_looks']} independent looks in {shifted['frames']} frames" in line, line
    assert "alarm raised" in line
