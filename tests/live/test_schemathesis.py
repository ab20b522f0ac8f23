"""Property-based API testing with schemathesis against the committed OpenAPI document.

Plain (no hooks, no configuration), schemathesis's stateful phase reaches a successful predict from
the document's example and follows the link from its answer to the feedback operation.

With the project's hooks, a running server (admin enabled, so the admin routes are exercised with
the token) gets generated requests from ``openapi/openapi.json`` in every phase, stateful
included, under every check schemathesis has (``--checks all``: no 5xx, every status, content
type, header and body as documented, schema-violating requests refused, Allow on 405, ...), told
in schemathesis.toml what JSON Schema cannot say. The requests are counted on the server side,
from its Prometheus counter.
"""

from __future__ import annotations

import json
import re
import subprocess
from collections.abc import Iterator
from pathlib import Path

import pytest

from service.infra.settings import PACKAGE_ROOT
from tests.live.server import LiveServer
from tests.service_calls import ADMIN_TOKEN

CONFIG = Path(__file__).with_name("schemathesis.toml")
DOCUMENT = PACKAGE_ROOT / "openapi" / "openapi.json"
MIN_REQUESTS = 500
LINKS = re.compile(r"API Links:\s+(\d+) covered / (\d+) selected")
SAMPLE = re.compile(r'^cks_http_requests_total\{method="(\w+)",route="(.*)",status="(\d+)"\}\s+(\S+)$')


@pytest.fixture(scope="module")
def fuzzed_server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[LiveServer]:
    with LiveServer(tmp_path_factory.mktemp("schemathesis") / "data", admin_token=ADMIN_TOKEN) as live:
        yield live


def requests_by_status(server: LiveServer) -> dict[tuple[str, str, str], float]:
    counts = {}
    for line in server.client.get("/metrics").text.splitlines():
        match = SAMPLE.match(line)
        if match:
            counts[match.group(1, 2, 3)] = float(match.group(4))
    return counts


def document_links() -> set[str]:
    """The document's links, named as schemathesis names a transition: source -> [status] name -> target."""
    paths = json.loads(DOCUMENT.read_text())["paths"]
    operations = [
        (f"{method.upper()} {path}", op) for path, ops in paths.items() for method, op in ops.items()
    ]
    targets = {op["operationId"]: label for label, op in operations}
    return {
        f"{label} -> [{status}] {name} -> {targets[link['operationId']]}"
        for label, op in operations
        for status, response in op["responses"].items()
        for name, link in response.get("links", {}).items()
    }


def test_no_server_errors_on_generated_requests(fuzzed_server: LiveServer, tmp_path: Path) -> None:
    before = requests_by_status(fuzzed_server)
    command = [
        "schemathesis",
        "--config-file",
        str(CONFIG),
        "run",
        str(DOCUMENT),
        "--url",
        fuzzed_server.url,
        "--header",
        f"Authorization: Bearer {ADMIN_TOKEN}",
        "--checks",
        "all",
        "--phases",
        "examples,coverage,fuzzing,stateful",
        "--max-examples",
        "60",  # with 40 the stateful phase ran 30 scenarios, too few to follow all 12 named links
        "--workers",
        "1",  # CPython 3.11's ast.parse is not thread-safe under hypothesis
        "--seed",
        "20240607",
        "--request-timeout",
        "30",
        "--no-color",
    ]
    env = {
        **fuzzed_server.env,
        "SCHEMATHESIS_HOOKS": "tests.live.schemathesis_hooks",
        "FUZZED_SERVER_URL": fuzzed_server.url,  # the hooks wait for jobs to end there
        "FUZZED_SERVER_TOKEN": ADMIN_TOKEN,
        "FUZZED_LINKS_FILE": str(tmp_path / "links.json"),
    }
    result = subprocess.run(command, cwd=tmp_path, env=env, capture_output=True, text=True, timeout=420)
    output = result.stdout[-6000:] + result.stderr[-3000:]
    after = requests_by_status(fuzzed_server)

    sent = {key: after[key] - before.get(key, 0) for key in after if after[key] != before.get(key, 0)}
    sent.pop(("GET", "/metrics", "200"), None)  # our own scrape
    server_errors = {key: n for key, n in sent.items() if key[2].startswith("5")}
    assert not server_errors, (
        f"5xx responses: {server_errors}\n{output}\nserver log:\n{fuzzed_server.log()[-6000:]}"
    )
    assert result.returncode == 0, output
    total = sum(sent.values())
    print(f"schemathesis: {total:g} requests reached the server, none answered 5xx\n{output}")
    print({key: n for key, n in sorted(sent.items()) if key[0] == "POST"})
    assert total >= MIN_REQUESTS, f"only {total:g} requests reached the server: {sent}\n{output}"
    routes = {route for _, route, _ in sent}
    assert {"/v1/predict", "/v1/admin/calibrations", "/v1/admin/calibrations/{version}/activate"} <= routes
    assert ("POST", "/v1/admin/calibrations", "202") in sent, "no upload was accepted: the hooks' zip is off"
    assert ("POST", "/v1/admin/forms/calibrations", "202") in sent, "no form upload was accepted"
    assert ("POST", "/v1/admin/audits", "202") in sent, "no audit was accepted"
    for predict in ("/v1/predict", "/v1/predict/form", "/v1/predict/png", "/v1/predict/batch"):
        assert ("POST", predict, "200") in sent, f"no successful {predict}: the hooks' image is off"
    assert ("GET", "/v1/admin/jobs/{job_id}", "200") in sent, "no job was read"
    assert ("GET", "/v1/admin/audits/{audit_id}", "200") in sent, "no link led from a job to its audit"
    followed = set(json.loads((tmp_path / "links.json").read_text()))  # written by the hooks
    print(f"stateful phase: {len(followed)} links followed: {sorted(followed)}")
    named = document_links()
    assert len(named) >= 11, f"the document names fewer links than the job routes give: {sorted(named)}"
    missing = named - followed
    assert not missing, f"links the stateful phase never followed: {sorted(missing)}\n{output}"


def test_a_plain_run_follows_the_feedback_link(fuzzed_server: LiveServer, tmp_path: Path) -> None:
    """No hooks: the predict example (retained) answers with a prediction_id, which the link takes to
    POST /v1/feedback/{prediction_id}. (An upload's zip is beyond a fuzzer: docs/api.md says so.)"""
    command = ["schemathesis", "run", str(DOCUMENT), "--url", fuzzed_server.url]
    command += ["--header", f"Authorization: Bearer {ADMIN_TOKEN}", "--phases", "stateful"]
    command += ["--include-operation-id", "predict", "--include-operation-id", "send_feedback"]
    command += ["--checks", "not_a_server_error", "--max-examples", "40", "--no-color"]
    result = subprocess.run(command, cwd=tmp_path, capture_output=True, text=True, timeout=300)
    output = result.stdout[-6000:] + result.stderr[-3000:]
    assert result.returncode == 0, output
    links = LINKS.search(result.stdout)
    assert links is not None, output
    assert links.group(1) == links.group(2) == "1", f"the feedback link was not followed:\n{output}"
