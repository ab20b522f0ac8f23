"""/docs and /redoc work without internet: a real Chromium, every request off 127.0.0.1 refused.

The pages are opened in Debian's ``chromium`` (driven by Playwright, whose own browser
download is not needed) against a real server. Every request for anything but the server
is aborted and recorded, and the test fails if there was one; screenshots of both pages are
written to the test's temporary directory (their paths are printed).
"""

from __future__ import annotations

import json
import re
from collections.abc import Iterator
from dataclasses import dataclass, field
from pathlib import Path
from urllib.parse import urlsplit

import pytest
from playwright.sync_api import (
    Browser,
    BrowserContext,
    Page,
    Request,
    Response,
    Route,
)

from service.serving.app import DOCS_CONTENT_SECURITY_POLICY, DOCS_PAGES
from tests.live.server import LiveServer

pytestmark = pytest.mark.browser

HTTP_METHODS = {"get", "put", "post", "delete", "options", "head", "patch", "trace"}
# ReDoc 2 always renders Redocly's logo from this address in its side menu; the pages'
# Content-Security-Policy stops the browser before it asks the network for it.
REDOC_LOGO = "https://cdn.redoc.ly/redoc/logo-mini.svg"
RECORD_POLICY_VIOLATIONS = """
window.__policyViolations = [];
document.addEventListener(
    "securitypolicyviolation", (event) => window.__policyViolations.push(event.blockedURI)
);
"""


@dataclass
class Watch:
    """What one browser context asked for and what went wrong on its pages."""

    server_host: str
    allowed_policy_violations: frozenset[str] = frozenset()
    elsewhere: list[str] = field(default_factory=list)
    failed: list[str] = field(default_factory=list)
    page_errors: list[str] = field(default_factory=list)

    def route(self, route: Route) -> None:
        if self.to_server(route.request.url):
            route.continue_()
        else:
            self.elsewhere.append(route.request.url)
            route.abort("internetdisconnected")

    def to_server(self, url: str) -> bool:
        return urlsplit(url).hostname == self.server_host

    def request_failed(self, request: Request) -> None:
        if self.to_server(request.url):  # the others: aborted above, or refused by the page's policy
            self.failed.append(f"{request.url}: {request.failure}")

    def response(self, response: Response) -> None:
        if response.status >= 400:
            self.failed.append(f"{response.url}: {response.status}")

    def assert_offline(self, page: Page) -> None:
        assert not self.elsewhere, f"the page asked for addresses other than the server: {self.elsewhere}"
        refused = set(page.evaluate("window.__policyViolations")) - self.allowed_policy_violations
        assert not refused, f"the page tried to load {sorted(refused)} (its policy refused them)"

    def assert_offline_and_clean(self, page: Page) -> None:
        self.assert_offline(page)
        assert not self.failed, f"requests to the server failed: {self.failed}"
        assert not self.page_errors, f"JavaScript errors on the page: {self.page_errors}"


@pytest.fixture
def context(browser: Browser, server: LiveServer) -> Iterator[tuple[BrowserContext, Watch]]:
    yield from watched_context(browser, server, {"width": 1280, "height": 1000})


def watched_context(
    browser: Browser, server: LiveServer, viewport: dict[str, int]
) -> Iterator[tuple[BrowserContext, Watch]]:
    """A browser context whose every request off the server is aborted and recorded."""
    context = browser.new_context(viewport=viewport)  # type: ignore[arg-type]
    watch = Watch(server_host=urlsplit(server.url).hostname or "")
    context.route("**/*", watch.route)
    context.add_init_script(RECORD_POLICY_VIOLATIONS)
    context.on("requestfailed", watch.request_failed)
    context.on("response", watch.response)
    yield context, watch
    context.close()


def open_page(
    context: tuple[BrowserContext, Watch], url: str, allowed_policy_violations: frozenset[str] = frozenset()
) -> tuple[Page, Watch]:
    browser_context, watch = context
    watch.allowed_policy_violations = allowed_policy_violations
    page = browser_context.new_page()
    page.on("pageerror", lambda error: watch.page_errors.append(str(error)))
    page.goto(url)
    watch.assert_offline(page)  # the page's scripts and styles are in: fail now, not at a timeout
    return page, watch


def screenshot(page: Page, path: Path) -> None:
    page.screenshot(path=path)
    print(f"screenshot: {path}")


def operations(server: LiveServer) -> set[tuple[str, str]]:
    """(METHOD, path) of every operation in the served OpenAPI document."""
    paths = server.client.get("/openapi.json").json()["paths"]
    return {
        (method.upper(), path) for path, item in paths.items() for method in item if method in HTTP_METHODS
    }


@pytest.mark.parametrize("page_path", DOCS_PAGES)
def test_pages_reference_only_their_own_server(server: LiveServer, page_path: str) -> None:
    response = server.client.get(page_path)
    assert response.status_code == 200, response.text
    assert not re.findall(r"\w+://[^\s\"'<>]+", response.text), "the page names another host"
    assert response.headers["content-security-policy"] == DOCS_CONTENT_SECURITY_POLICY


def test_swagger_ui_lists_every_operation_and_tries_get_model(
    server: LiveServer, context: tuple[BrowserContext, Watch], tmp_path: Path
) -> None:
    page, watch = open_page(context, f"{server.url}/docs")
    page.wait_for_selector(".opblock-summary")
    listed = page.eval_on_selector_all(
        ".opblock-summary",
        """blocks => blocks.map(block => [
            block.querySelector(".opblock-summary-method").textContent.toUpperCase(),
            block.querySelector(".opblock-summary-path").dataset.path,
        ])""",
    )
    assert {tuple(item) for item in listed} == operations(server)

    block = page.locator(".opblock-get", has=page.locator(".opblock-summary-path[data-path='/v1/model']"))
    block.locator(".opblock-summary-control").click()
    block.get_by_role("button", name="Try it out").click()
    block.get_by_role("button", name="Execute").click()
    result = block.locator(".live-responses-table .response")
    result.locator(".response-col_status", has_text="200").wait_for()
    shown = json.loads(result.locator(".response-col_description pre").first.inner_text())
    assert shown == server.client.get("/v1/model").json()
    result.scroll_into_view_if_needed()
    screenshot(page, tmp_path / "docs.png")
    watch.assert_offline_and_clean(page)


def test_redoc_lists_every_operation(
    server: LiveServer, context: tuple[BrowserContext, Watch], tmp_path: Path
) -> None:
    page, watch = open_page(context, f"{server.url}/redoc", frozenset({REDOC_LOGO}))
    page.wait_for_selector(".http-verb")
    listed = page.eval_on_selector_all(
        ".http-verb",
        "verbs => verbs.map(verb => [verb.textContent.toUpperCase(), verb.nextSibling.textContent])",
    )
    assert {tuple(item) for item in listed} == operations(server)
    screenshot(page, tmp_path / "redoc.png")
    watch.assert_offline_and_clean(page)
