"""The operator console in a real Chromium with every request off 127.0.0.1 refused: it loads
without errors, asks for the admin token, then shows the model, the versions, the activation
history, the audit run here (its coverage plotted against the bands), the live coverage of the
field labels sent here (per version and group: coverage so far, the confidence sequence, the
promise, the alarm), the drift of every keypoint over time and the set sizes of the predictions
made here, or 'no drift data' (and no feedback) on a server without drift monitoring; at 1280 px
and at a phone's 390 px nothing is cut or pushed out of its panel or the window, no word or
number is split across lines, and no control shows empty (without a token, without audits).
On a camera stream, after 300 frames of one static scene it says "no alarm" on one independent
look; after heavily occluded scenes, "alarm raised", with the looks and frames the drift API
reports (tests/live/test_drift_streams.py sends the same stream).
Screenshots go to the test's temporary directory and to ``test-artifacts/console*.png``
(gitignored). The services run in this process on loopback ports (tests/api/in_process.py), but
the one without drift monitoring, a process: its metrics must be its own."""

from __future__ import annotations

import re
import shutil
import struct
import time
from collections.abc import Iterator
from contextlib import contextmanager
from decimal import ROUND_HALF_UP, Decimal
from pathlib import Path
from urllib.parse import urlsplit

import httpx
import pytest
from playwright.sync_api import Browser, BrowserContext, ConsoleMessage

from service.api.monitoring.console_routes import CONSOLE_CONTENT_SECURITY_POLICY
from service.infra.settings import PACKAGE_ROOT
from tests.api.in_process import OnLoopback
from tests.api.test_audits import run_audit, shifted
from tests.api.test_feedback import send_all
from tests.deploy.test_api_pages import RECORD_POLICY_VIOLATIONS, Watch, open_page, watched_context
from tests.live.server import LiveServer
from tests.live.test_drift_streams import send_heavy_until_alarm, send_static_scene
from tests.predict_client import instances_of, predict_ok
from tests.samples import Sample, batch_zip, samples_by_image
from tests.service_calls import ADMIN_TOKEN

pytestmark = pytest.mark.browser

ARTIFACT = PACKAGE_ROOT / "test-artifacts" / "console.png"
HISTORY_SECONDS = 0.5


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[OnLoopback]:
    """A server whose drift history takes a point every half second."""
    data = tmp_path_factory.mktemp("console") / "data"
    with OnLoopback(data, {"DRIFT_HISTORY_SECONDS": HISTORY_SECONDS}, admin_token=ADMIN_TOKEN) as served:
        yield served


@pytest.fixture(scope="module")
def predictions(server: OnLoopback, samples: list[Sample]) -> None:
    """Three rounds of predictions on the samples, a few history points apart."""
    for round_ in range(3):
        for path, group in samples_by_image(samples).items():
            kind = ("cov", "peak", "var")[round_]
            predict_ok(
                server.client, path.read_bytes(), {"instances": instances_of(group), "nonconformity": kind}
            )
        time.sleep(3 * HISTORY_SECONDS)


@pytest.fixture(scope="module")
def feedback(server: OnLoopback, samples: list[Sample]) -> None:
    """Field labels of every sample: true ones from one camera (answers of difficulty strata), and
    labels 60 px off from another (its sets miss them: its alarm is raised)."""
    send_all(server, samples, 0.0, "cam-true", stratify="difficulty")  # type: ignore[arg-type]
    send_all(server, samples, 60.0, "cam-moved")  # type: ignore[arg-type]


@pytest.fixture
def context(browser: Browser, server: OnLoopback) -> Iterator[tuple[BrowserContext, Watch]]:
    yield from watched_context(browser, server, {"width": 1400, "height": 1350})


@pytest.fixture(scope="module")
def audit(server: OnLoopback, samples_dir: Path, coco: dict) -> dict:
    return run_audit(server, batch_zip(samples_dir, coco, mutate=shifted(5)), name="console-test")


def to_fixed(value: float, digits: int = 3) -> str:
    """JavaScript's ``value.toFixed(digits)``: a tie goes up (0.3125 -> 0.313), not to even as in Python."""
    return str(Decimal(value).quantize(Decimal(10) ** -digits, rounding=ROUND_HALF_UP))


def test_the_console_names_the_variant_that_serves(browser: Browser, tmp_path: Path) -> None:
    int8 = PACKAGE_ROOT / "models" / "lmo-synth-unet-int8"
    with OnLoopback(tmp_path / "data", model_dir=int8) as fast:
        contexts = watched_context(browser, fast, {"width": 1280, "height": 900})  # type: ignore[arg-type]
        page, _ = open_page(next(contexts), f"{fast.url}/console")
        page.wait_for_selector("#model table")
        assert "variant\tint8, of lmo-synth-unet" in page.inner_text("#model")
        next(contexts, None)  # closes the browser context


def test_the_console_is_served_from_the_package_without_other_hosts(server: OnLoopback) -> None:
    for path in ("/console", "/console/console.js", "/console/console.css"):
        response = server.client.get(path)
        assert response.status_code == 200, path
        assert response.headers["content-security-policy"] == CONSOLE_CONTENT_SECURITY_POLICY
        assert not re.findall(r"https?://(?!www\.w3\.org/2000/svg)[^\s\"'<>]+", response.text), path
    assert server.client.get("/console/secrets.txt").status_code == 404
    assert server.client.get("/console/../v1/model").status_code in (200, 404)  # no file outside the folder


def test_the_console_shows_the_audit_against_its_bands(
    server: OnLoopback,
    context: tuple[BrowserContext, Watch],
    audit: dict,
    predictions: None,
    feedback: None,
    tmp_path: Path,
) -> None:
    errors: list[str] = []
    page, watch = open_page(context, f"{server.url}/console")
    page.on("console", lambda message: _record_error(message, errors))
    page.wait_for_selector("#model table")
    assert "Enter the admin token" in page.inner_text("#audits")  # nothing admin without the token
    assert server.client.get("/v1/model").json()["hash"] in page.inner_text("#model")
    assert "variant\toriginal" in page.inner_text("#model")

    page.fill("#token", server.admin_token)
    page.click("#token-form button[type=submit]")
    page.wait_for_selector("body[data-loaded=true]")
    report = audit["report"]
    section = next(
        s
        for s in report["sections"]
        if (s["nonconformity"], s["epsilon"], s["scope"]) == ("cov", 0.1, "keypoint")
    )
    points = page.locator("#audit-plot circle.coverage")
    assert points.count() == len([k for k in section["keypoints"] if k["coverage"] is not None])
    assert page.locator("#audit-plot line.whisker").count() == len(section["keypoints"])
    flagged = {k["keypoint"] for k in section["keypoints"] if k["flagged"]}
    keypoints_of = "circles => circles.map(circle => circle.dataset.keypoint)"
    shown = set(page.eval_on_selector_all("#audit-plot circle.flagged", keypoints_of))
    assert shown == flagged and flagged
    assert f"Audit #{audit['id']} of version {audit['version']}" in page.inner_text("#audit-detail")
    page.click("#audit-detail summary:has-text('What to do')")  # the advice, folded
    assert "Recalibrate" in page.inner_text("#audit-detail")

    versions = server.client.get("/v1/admin/calibrations", headers=server.admin).json()["versions"]
    assert page.locator("#versions .body > table > tbody > tr").count() == min(10, len(versions))
    activations = server.client.get("/v1/admin/activations", headers=server.admin).json()["activations"]
    assert page.locator("#activations tbody tr").count() == len(activations)
    _assert_drift_panels(server, page)
    _assert_live_coverage(server, page)

    page.select_option("#audit-epsilon", "0.2")  # another epsilon redraws the plot
    section = next(
        s
        for s in report["sections"]
        if (s["nonconformity"], s["epsilon"], s["scope"]) == ("cov", 0.2, "keypoint")
    )
    flagged = {k["keypoint"] for k in section["keypoints"] if k["flagged"]}
    flagged_points = "document.querySelectorAll('#audit-plot circle.flagged').length"
    page.wait_for_function(f"{flagged_points} === {len(flagged)}")
    page.select_option("#audit-epsilon", "0.1")

    page.screenshot(path=tmp_path / "console.png", full_page=True)
    ARTIFACT.parent.mkdir(exist_ok=True)
    shutil.copyfile(tmp_path / "console.png", ARTIFACT)
    print(f"screenshot: {tmp_path / 'console.png'}, copied to {ARTIFACT}")

    page.reload()  # the token stays for the tab
    page.wait_for_selector("body[data-loaded=true]")
    assert page.locator("#audit-plot circle.coverage").count() == points.count()
    page.click("#forget")
    page.wait_for_function("!sessionStorage.getItem('cks-admin-token')")
    assert "Enter the admin token" in page.inner_text("#versions")
    watch.assert_offline_and_clean(page)
    assert not errors, f"console errors: {errors}"


# Every element drawn on the page: where it reaches beyond the window or the section holding it,
# or cuts its own content (a scrolled or clipped box narrower than what it holds).
CUT_OR_HIDDEN = """() => {
  const width = document.documentElement.clientWidth;
  const name = (el) => el.tagName.toLowerCase() + (el.id ? '#' + el.id : '') +
    ` "${(el.textContent || '').trim().slice(0, 40)}"`;
  const problems = [], reported = [];
  const say = (el, text) => { reported.push(el); problems.push(`${name(el)} ${text}`); };
  if (document.documentElement.scrollWidth > width) {
    problems.push(`the page scrolls sideways: ${document.documentElement.scrollWidth} px > ${width}`);
  }
  for (const el of document.querySelectorAll('body *')) {
    const box = el.getBoundingClientRect();
    if ((!box.width && !box.height) || reported.some((outer) => outer.contains(el))) continue;
    const span = `${Math.round(box.left)}..${Math.round(box.right)}`;
    if (box.left < -0.5 || box.right > width + 0.5) say(el, `reaches ${span} of ${width} px`);
    const section = el.parentElement.closest('section, header');
    const outer = section && section.getBoundingClientRect();
    if (outer && (box.left < outer.left - 0.5 || box.right > outer.right + 0.5)) {
      const where = `${section.id || 'header'} ${Math.round(outer.left)}..${Math.round(outer.right)}`;
      say(el, `reaches ${span} out of its ${where}`);
    }
    const style = getComputedStyle(el);
    if (style.overflowX !== 'visible' && el.scrollWidth > el.clientWidth + 1) {
      say(el, `cuts its content: ${el.scrollWidth} px in ${el.clientWidth}`);
    }
  }
  return problems;
}"""


# Every word or number on the page drawn over more than one line ("246/6" for 2466, "ad/min"),
# and every visible control with nothing in it (an empty drop-down). A hash (in <code>) is wider
# than a phone and may break; a line may break after a hyphen or a dash, so those end a word.
SPLIT_OR_EMPTY = """() => {
  const problems = [];
  const shown = (el) => el.getClientRects().length > 0 && getComputedStyle(el).visibility !== 'hidden';
  const name = (el) => el.tagName.toLowerCase() + (el.id ? '#' + el.id : '');
  const walker = document.createTreeWalker(document.body, NodeFilter.SHOW_TEXT);
  for (let node = walker.nextNode(); node; node = walker.nextNode()) {
    const parent = node.parentElement;
    if (!parent || parent.closest('code, svg, script, style') || !shown(parent)) continue;
    for (const word of node.data.matchAll(/[^\\s\\-\u2013\u2014]+/g)) {
      const range = document.createRange();
      range.setStart(node, word.index);
      range.setEnd(node, word.index + word[0].length);
      const tops = [...range.getClientRects()].filter((r) => r.width > 0).map((r) => Math.round(r.top));
      if (new Set(tops).size > 1) {
        const where = parent.closest('section, header'), lines = new Set(tops).size;
        const place = `${name(parent)} of ${where ? name(where) : 'body'}`;
        problems.push(`"${word[0]}" split over ${lines} lines in ${place}`);
      }
    }
  }
  for (const control of document.querySelectorAll('select, button, label')) {
    if (!shown(control)) continue;
    const empty = control.tagName === 'SELECT' ? !control.options.length : !control.textContent.trim();
    if (empty) problems.push(`an empty ${name(control)}`);
  }
  return problems;
}"""


def png_width(path: Path) -> int:
    """The width in a PNG's IHDR chunk."""
    data = path.read_bytes()
    assert data.startswith(b"\x89PNG\r\n\x1a\n") and data[12:16] == b"IHDR", path
    return struct.unpack(">I", data[16:20])[0]


def check_and_save(page, name: str, tmp_path: Path) -> None:  # noqa: ANN001 - a Playwright Page
    """A full-page screenshot as wide as the window, kept in test-artifacts/; then no word split and
    no empty control on the page it shows."""
    shot = tmp_path / name
    page.screenshot(path=shot, full_page=True)
    ARTIFACT.parent.mkdir(exist_ok=True)
    shutil.copyfile(shot, ARTIFACT.with_name(name))
    assert png_width(shot) == page.viewport_size["width"], (
        f"{ARTIFACT.with_name(name)} is wider than the window"
    )

    problems = page.evaluate(SPLIT_OR_EMPTY)
    assert not problems, f"split or empty (screenshot {ARTIFACT.with_name(name)}): {problems}"


PHONE = (390, 844)  # a phone's window, in CSS pixels
KEYPOINT_ALARM_ROWS_HEIGHT = """[...document.querySelectorAll('#live-detail tr')]
  .filter((row) => row.cells[0] && row.cells[0].textContent.startsWith('keypoint: '))
  .reduce((sum, row) => sum + row.offsetHeight, 0)"""
# Panels of half the page's width whose row holds nothing beside them (an empty half-cell).
UNFILLED_ROWS = """() => {
  const main = document.querySelector("main").getBoundingClientRect();
  const sections = [...document.querySelectorAll("main > section")];
  const halves = sections.filter((s) => s.offsetWidth < 0.75 * main.width);
  return halves.filter((s) => !halves.some((t) => t !== s && t.offsetTop === s.offsetTop)).map((s) => s.id);
}"""


@pytest.fixture(params=[1280, PHONE[0]], ids=["laptop", "phone"])
def window(request: pytest.FixtureRequest, browser: Browser, server: OnLoopback) -> Iterator[tuple]:
    """A laptop's window, 1280 px wide, or a phone's, 390 x 844 px."""
    height = PHONE[1] if request.param == PHONE[0] else 900
    yield from watched_context(browser, server, {"width": request.param, "height": height})


def test_the_console_fits_a_laptop_and_a_phone(
    server: OnLoopback,
    window: tuple[BrowserContext, Watch],
    audit: dict,
    predictions: None,
    feedback: None,
    tmp_path: Path,
) -> None:
    page, watch = open_page(window, f"{server.url}/console")
    width = page.viewport_size["width"]
    page.wait_for_selector("#model table")
    assert "Enter the admin token" in page.inner_text("#audits")
    check_and_save(page, f"console-{width}-no-token.png", tmp_path)  # no empty drop-downs either
    page.fill("#token", server.admin_token)
    page.click("#token-form button[type=submit]")
    page.wait_for_selector("body[data-loaded=true]")
    check_and_save(page, f"console-{width}-folded.png", tmp_path)
    assert not page.evaluate(UNFILLED_ROWS), "a panel stands alone in a row of two"
    assert not re.search(r"[.!?] [a-z]", page.inner_text("main")), "a sentence starts in lower case"
    if width == PHONE[0]:  # before any detail is opened: at most three screens, the hash on two lines
        # beside the totals, every group whose alarm is raised is listed: how many depends on the data
        # (with the bundled calibration, two keypoints whose labels the moved camera shares), not the layout
        listed = page.evaluate(KEYPOINT_ALARM_ROWS_HEIGHT)
        assert page.evaluate("document.documentElement.scrollHeight") - listed <= 3 * PHONE[1]
        assert page.evaluate("document.querySelector('#model code').getClientRects().length") <= 2
    page.eval_on_selector_all("details", "all => all.forEach((details) => { details.open = true; })")
    page.select_option("#live-level", "all")  # every live coverage group drawn
    name = f"console-{width}.png"
    check_and_save(page, name, tmp_path)
    problems = page.evaluate(CUT_OR_HIDDEN)
    assert not problems, f"cut or hidden (screenshot {ARTIFACT.with_name(name)}): {problems}"
    watch.assert_offline_and_clean(page)  # the favicon too: no 404


def test_the_service_has_a_favicon(server: OnLoopback) -> None:
    icon = server.client.get("/favicon.ico")
    assert icon.status_code == 200 and icon.headers["content-type"] == "image/svg+xml"
    assert icon.content == server.client.get("/console/favicon.svg").content


def test_a_wrong_token_is_told_not_hidden(server: OnLoopback, context: tuple[BrowserContext, Watch]) -> None:
    browser_context, watch = context
    page = browser_context.new_page()
    page.goto(f"{server.url}/console")
    page.wait_for_selector("#model table")
    page.fill("#token", "not-the-token")
    page.click("#token-form button[type=submit]")
    page.wait_for_selector("body[data-loaded=true]")
    assert "admin token was refused" in page.inner_text("#versions")
    watch.failed.clear()  # the 401s are the point here
    watch.assert_offline(page)


def _record_error(message: ConsoleMessage, errors: list[str]) -> None:
    if message.type == "error":
        errors.append(f"{message.text} ({message.location.get('url')})")


def _assert_drift_panels(server: OnLoopback, page) -> None:  # noqa: ANN001 - a Playwright Page
    """Drift as the server reports it: a row per keypoint with its statistics over time, and a
    histogram of set sizes per nonconformity function predicted with."""
    drift = server.client.get("/v1/admin/drift", headers=server.admin).json()
    assert page.locator("#drift tbody tr").count() == len(drift["keypoints"]) > 0
    assert len(drift["history"]) >= 2
    with_history = {i for point in drift["history"] for i, v in enumerate(point["keypoint_statistics"]) if v}
    assert page.locator("#drift svg.sparkline").count() >= len(with_history) > 0
    kinds = {kind for kind, sizes in drift["set_sizes"].items() if sizes["n"] and sizes["semi_major_px"]}
    shown = set(
        page.eval_on_selector_all("#set-sizes svg.histogram", "plots => plots.map(p => p.dataset.kind)")
    )
    assert shown == kinds == {"cov", "peak", "var"}


def test_a_server_without_drift_says_so(browser: Browser, tmp_path: Path) -> None:
    with LiveServer(tmp_path / "data", admin_token=ADMIN_TOKEN, drift_enabled=False) as live:
        context = browser.new_context()
        watch = Watch(server_host=urlsplit(live.url).hostname or "")
        context.route("**/*", watch.route)
        context.add_init_script(RECORD_POLICY_VIOLATIONS)
        context.on("requestfailed", watch.request_failed)
        page = context.new_page()
        page.on("pageerror", lambda error: watch.page_errors.append(str(error)))
        page.goto(f"{live.url}/console")
        page.fill("#token", ADMIN_TOKEN)
        page.click("#token-form button[type=submit]")
        page.wait_for_selector("body[data-loaded=true]")
        assert "No drift data" in page.inner_text("#drift")
        assert "not available" in page.inner_text("#set-sizes")
        assert "No coverage audit yet" in page.inner_text("#audits")
        assert "No labelled feedback yet" in page.inner_text("#live-coverage")
        for width in (1280, 390):
            page.set_viewport_size({"width": width, "height": 900})
            check_and_save(page, f"console-{width}-no-audits.png", tmp_path)
        # The metrics are the process's: a server without drift exports no cks_drift_* at all.
        assert "cks_drift_" not in httpx.get(f"{live.url}/metrics").text
        watch.assert_offline(page)
        assert not watch.page_errors
        context.close()


def _assert_live_coverage(server: OnLoopback, page) -> None:  # noqa: ANN001 - a Playwright Page
    """Live coverage as the admin API reports it: totals and alarms first, then every group with its
    coverage so far, confidence sequence, promise and alarm state, and each level on its own."""
    groups = server.client.get("/v1/admin/coverage/live", headers=server.admin).json()["groups"]
    alarmed = [g for g in groups if g["alarm"]]
    assert alarmed and any(g["level"] == "stream" and g["name"] == "cam-moved" for g in alarmed)
    summary = page.inner_text("#live-coverage .body")
    assert f"Alarm raised in {len(alarmed)} of {len(groups)} groups" in summary, summary
    rows = page.locator("#live-detail tbody tr")
    assert rows.count() == len([g for g in groups if g["level"] == "version" or g["alarm"]])
    assert "alarm raised" in page.inner_text("#live-detail")

    page.select_option("#live-level", "all")
    assert rows.count() == len(groups)
    drawn = "plots => plots.map(p => p.dataset.level + ' ' + p.dataset.name)"
    shown = page.eval_on_selector_all("#live-detail svg.live-interval", drawn)
    assert sorted(shown) == sorted(f"{g['level']} {g['name']}" for g in groups)
    for group in groups:
        label = "all keypoints" if group["level"] == "version" else f"{group['level']}: {group['name']}"
        row = rows.filter(
            has=page.locator(f'svg[data-level="{group["level"]}"][data-name="{group["name"]}"]')
        )
        cells = row.locator("td").all_inner_texts()
        assert cells[0] == label and cells[1] == str(group["labelled"]) and cells[3] == str(group["looks"])
        assert cells[2] == to_fixed(group["covered"] / group["labelled"])
        assert cells[5] == f"{to_fixed(group['lower'])}–{to_fixed(group['upper'])}"
        assert cells[7] == f"≥ {group['floor']:.3f}"
        assert cells[8] == ("alarm raised" if group["alarm"] else "no alarm")

    page.select_option("#live-level", "stratum")  # the Mondrian strata the true camera was answered by
    strata = [g for g in groups if g["level"] == "stratum"]
    assert rows.count() == len(strata) > 1
    page.select_option("#live-level", "summary")


def _drift_line(context: tuple[BrowserContext, Watch], server: OnLoopback) -> str:
    page, watch = open_page(context, f"{server.url}/console")
    page.wait_for_selector("#model table")
    page.fill("#token", ADMIN_TOKEN)
    page.click("#token-form button[type=submit]")
    page.wait_for_selector("body[data-loaded=true]")
    text = page.inner_text("#drift p.muted")
    watch.assert_offline_and_clean(page)
    page.close()
    return text


def test_the_console_shows_a_quiet_static_scene_then_the_alarm(browser: Browser, tmp_path: Path) -> None:
    viewport = {"width": 1400, "height": 1000}
    with (
        OnLoopback(tmp_path / "data", admin_token=ADMIN_TOKEN) as streamed,
        contextmanager(watched_context)(browser, streamed, viewport) as context,
    ):
        quiet = send_static_scene(streamed)
        line = _drift_line(context, streamed)
        assert f"{quiet['independent_looks']} independent looks in {quiet['frames']} frames" in line, line
        assert "no alarm" in line and "alarm raised" not in line

        _, shifted = send_heavy_until_alarm(streamed)
        line = _drift_line(context, streamed)
        assert f"{shifted['independent_looks']} independent looks in {shifted['frames']} frames" in line, line
        assert "alarm raised" in line
