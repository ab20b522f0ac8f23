"""Logs people can use, read from real servers' stderr: one format for the service's lines and
uvicorn's (text or JSON), an access line per request, the request id on every line of a
request and in every problem body, admin actions with who, what and outcome."""

from __future__ import annotations

import json
import re
import subprocess
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from pathlib import Path
from typing import Any

import httpx
import pytest

from service.infra.settings import PACKAGE_ROOT
from tests.live.server import LiveServer, cli, free_port, service_env
from tests.predict_client import instances_of, predict_multipart
from tests.samples import Sample, batch_zip, samples_by_image
from tests.service_calls import ADMIN_TOKEN, assert_problem, wait_until

# 2026-01-31T12:00:00.123Z INFO uvicorn.error [-] Started server process [123]
TEXT_LINE = re.compile(
    r"(?P<time>\d{4}-\d\d-\d\dT\d\d:\d\d:\d\d\.\d{3}Z) (?P<level>DEBUG|INFO|WARNING|ERROR|CRITICAL) "
    r"(?P<logger>[\w.]+) \[(?P<request_id>[^\]\s]+)\] (?P<message>.*)"
)
GENERATED_ID = re.compile(r"[0-9a-f]{32}")


def text_lines(log: str) -> list[dict[str, str]]:
    """Every line of a text log, parsed; a line that is not in the format fails the test."""
    parsed = []
    for line in log.splitlines():
        match = TEXT_LINE.fullmatch(line)
        assert match, f"not in the text log format: {line!r}"
        parsed.append(match.groupdict())
    return parsed


def json_lines(log: str) -> list[dict[str, Any]]:
    """Every line of a JSON log, parsed; each must be one JSON object with the common members."""
    parsed = []
    for line in log.splitlines():
        record = json.loads(line)
        assert isinstance(record, dict), line
        assert {"timestamp", "level", "logger", "message"} <= record.keys(), line
        parsed.append(record)
    return parsed


def first_image(samples: list[Sample]) -> tuple[bytes, dict]:
    path, group = next(iter(samples_by_image(samples).items()))
    return path.read_bytes(), {"instances": instances_of(group)}


def predict(client: httpx.Client, samples: list[Sample], request_id: str | None = None) -> httpx.Response:
    image, parameters = first_image(samples)
    response = predict_multipart(
        client, image, parameters, {"X-Request-ID": request_id} if request_id else None
    )
    assert response.status_code == 200, response.text
    return response


Line = dict[str, Any]


def wait_for_lines(
    read: Callable[[], list[Line]], condition: Callable[[Line], bool], what: str, count: int = 1
) -> list[Line]:
    """The parsed lines meeting ``condition``, once the server has written ``count`` of them."""
    found: list[Line] = []

    def written() -> bool:
        found[:] = [line for line in read() if condition(line)]
        return len(found) >= count

    wait_until(written, what)
    return found


def wait_for_line(read: Callable[[], list[Line]], condition: Callable[[Line], bool], what: str) -> Line:
    return wait_for_lines(read, condition, what)[0]


# ----------------------------------------------------------------- text, python -m uvicorn


@pytest.fixture(scope="module")
def text_server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[LiveServer]:
    with LiveServer(tmp_path_factory.mktemp("text") / "data", admin_token=ADMIN_TOKEN) as live:
        yield live


def test_text_access_line_of_a_predict(text_server: LiveServer, samples: list[Sample]) -> None:
    response = predict(text_server.client, samples, "text-predict-1")
    assert response.headers["X-Request-ID"] == "text-predict-1"
    version = response.json()["calibration"]["version"]

    line = wait_for_line(
        lambda: text_lines(text_server.log()),
        lambda line: line["logger"] == "service.access" and line["request_id"] == "text-predict-1",
        "the predict's access line",
    )
    access = re.fullmatch(
        r"access method=POST path=/v1/predict status=200 duration_ms=(?P<ms>[0-9.]+)"
        r" calibration_version=(?P<version>\d+) client=127\.0\.0\.1",
        line["message"],
    )
    assert access, line
    assert float(access["ms"]) > 0 and int(access["version"]) == version == 1
    assert line["level"] == "INFO"


def test_uvicorn_start_up_lines_are_in_the_service_format(text_server: LiveServer) -> None:
    lines = text_lines(text_server.log())  # every line parses, the service's and uvicorn's
    uvicorn = [line["message"] for line in lines if line["logger"] == "uvicorn.error"]
    assert any(message.startswith("Started server process") for message in uvicorn), lines
    assert "Application startup complete." in uvicorn
    assert any(
        line["logger"] == "service.serving.container" and "serving model" in line["message"] for line in lines
    )
    outside_requests = [
        line for line in lines if line["logger"] in ("uvicorn.error", "service.serving.container")
    ]
    assert all(line["request_id"] == "-" for line in outside_requests), outside_requests
    assert not any(line["logger"] == "uvicorn.access" for line in lines), "uvicorn's own access log is on"


def test_the_request_id_is_echoed_or_generated(text_server: LiveServer) -> None:
    given = "Req-42_a.b:c/d+e=f@g~"
    assert (
        text_server.client.get("/healthz", headers={"X-Request-ID": given}).headers["X-Request-ID"] == given
    )
    longest = "x" * 128
    assert (
        text_server.client.get("/healthz", headers={"X-Request-ID": longest}).headers["X-Request-ID"]
        == longest
    )

    generated = {text_server.client.get("/healthz").headers["X-Request-ID"] for _ in range(3)}
    assert len(generated) == 3 and all(GENERATED_ID.fullmatch(value) for value in generated)

    for bad in ("has space", "x" * 129, "", "tab\there", "caf\u00e9"):
        response = text_server.client.get("/healthz", headers=[(b"X-Request-ID", bad.encode())])
        replaced = response.headers["X-Request-ID"]
        assert GENERATED_ID.fullmatch(replaced), (bad, replaced)
        wait_for_line(
            lambda: text_lines(text_server.log()),
            lambda line, rid=replaced: line["request_id"] == rid,
            f"the access line of the request that sent {bad!r}",
        )


def test_problem_bodies_carry_the_request_id(text_server: LiveServer) -> None:
    response = text_server.client.post("/v1/predict", json={}, headers={"X-Request-ID": "bad-body-1"})
    body = assert_problem(response, 422, "instances")
    assert body["request_id"] == response.headers["X-Request-ID"] == "bad-body-1"

    for response, status in [
        (text_server.client.get("/v1/no-such-route"), 404),
        (text_server.client.get("/v1/admin/calibrations"), 401),
        (text_server.client.post("/v1/predict", content=b"x", headers={"Content-Type": "text/plain"}), 415),
    ]:
        body = assert_problem(response, status)
        assert GENERATED_ID.fullmatch(body["request_id"]), body
        assert body["request_id"] == response.headers["X-Request-ID"]
        wait_for_line(
            lambda: text_lines(text_server.log()),
            lambda line, body=body, status=status: (
                line["request_id"] == body["request_id"] and f"status={status}" in line["message"]
            ),
            f"the access line of the {status}",
        )


def test_admin_actions_are_logged_with_who_what_outcome_and_the_request_id(
    text_server: LiveServer, samples_dir: Path, coco: dict
) -> None:
    headers = {**text_server.admin, "X-Request-ID": "activate-1"}
    response = text_server.client.post(
        "/v1/admin/calibrations/1/activate", json={"reason": "re-pin v1"}, headers=headers
    )
    assert response.status_code == 200, response.text
    audit, access = wait_for_lines(
        lambda: text_lines(text_server.log()),
        lambda line: line["request_id"] == "activate-1",
        "the audit and the access line of the activation",
        count=2,
    )
    assert (audit["logger"], access["logger"]) == ("service.audit", "service.access")
    assert audit["message"] == (
        "audit action=activation outcome=activated who=admin client=127.0.0.1 version=1 previous_version=1"
        ' reason="re-pin v1"'
    )

    refused = text_server.client.post(
        "/v1/admin/calibrations/99/activate",
        json={},
        headers={**text_server.admin, "X-Request-ID": "activate-2"},
    )
    assert_problem(refused, 404)
    line = wait_for_line(
        lambda: text_lines(text_server.log()),
        lambda line: line["request_id"] == "activate-2" and line["logger"] == "service.audit",
        "the audit line of the refused activation",
    )
    assert line["message"].startswith("audit action=activation outcome=refused who=admin"), line

    # the upload's audit entry is written on a worker thread: the id goes with it
    upload = text_server.client.post(
        "/v1/admin/calibrations",
        content=batch_zip(samples_dir, coco, images=2),
        headers={**text_server.admin, "Content-Type": "application/zip", "X-Request-ID": "upload-1"},
    )
    assert upload.status_code == 202, upload.text
    line = wait_for_line(
        lambda: text_lines(text_server.log()),
        lambda line: line["request_id"] == "upload-1" and line["logger"] == "service.audit",
        "the audit line of the upload",
    )
    assert line["message"].startswith("audit action=upload outcome=accepted who=admin"), line
    text_server.wait_job(upload.json()["id"])


# ----------------------------------------------------------------- JSON, keypoint-service serve


@contextmanager
def served(data_dir: Path, **settings: Any) -> Iterator[tuple[httpx.Client, Path]]:
    """``keypoint-service serve`` (uvicorn given the service's log_config) on a free port."""
    port = free_port()
    log = data_dir.parent / "serve.log"
    with open(log, "wb") as out:
        process = subprocess.Popen(
            [*cli(), "serve"],
            env=service_env(data_dir, port=port, **settings),
            cwd=PACKAGE_ROOT,
            stdout=out,
            stderr=subprocess.STDOUT,
        )
    client = httpx.Client(base_url=f"http://127.0.0.1:{port}", timeout=60)

    def answers() -> bool:
        assert process.poll() is None, log.read_text()
        try:
            return client.get("/healthz").status_code == 200
        except httpx.TransportError:
            return False

    try:
        wait_until(answers, "keypoint-service serve answers /healthz", timeout=60)
        yield client, log
    finally:
        client.close()
        process.terminate()
        process.wait(timeout=30)


@pytest.fixture(scope="module")
def json_server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[tuple[httpx.Client, Path]]:
    data = tmp_path_factory.mktemp("json") / "data"
    with served(data, log_format="json", admin_token=ADMIN_TOKEN) as server:
        yield server


def test_json_lines_parse_and_include_uvicorn_start_up(json_server: tuple[httpx.Client, Path]) -> None:
    _, log = json_server
    lines = json_lines(log.read_text())
    uvicorn = [line["message"] for line in lines if line["logger"] == "uvicorn.error"]
    assert any(message.startswith("Started server process") for message in uvicorn), lines
    assert any(message.startswith("Uvicorn running on") for message in uvicorn), lines
    assert not any("color_message" in line for line in lines), "uvicorn's ANSI copy of its message leaked"


def test_json_access_line_of_a_predict(json_server: tuple[httpx.Client, Path], samples: list[Sample]) -> None:
    client, log = json_server
    response = predict(client, samples)  # no X-Request-ID: the service makes one
    request_id = response.headers["X-Request-ID"]
    assert GENERATED_ID.fullmatch(request_id)

    line = wait_for_line(
        lambda: json_lines(log.read_text()),
        lambda line: line.get("request_id") == request_id,
        "the predict's access line",
    )
    assert line["logger"] == "service.access" and line["level"] == "INFO"
    assert (line["method"], line["path"], line["status"]) == ("POST", "/v1/predict", 200)
    assert isinstance(line["duration_ms"], float) and line["duration_ms"] > 0
    assert line["calibration_version"] == response.json()["calibration"]["version"] == 1


def test_json_every_line_of_a_request_carries_its_id(json_server: tuple[httpx.Client, Path]) -> None:
    client, log = json_server
    admin = {"Authorization": f"Bearer {ADMIN_TOKEN}", "X-Request-ID": "json-activate-1"}
    response = client.post("/v1/admin/calibrations/1/activate", json={"reason": "json"}, headers=admin)
    assert response.status_code == 200, response.text
    audit, access = wait_for_lines(
        lambda: json_lines(log.read_text()),
        lambda line: line.get("request_id") == "json-activate-1",
        "the audit and the access line",
        count=2,
    )
    assert audit["logger"] == "service.audit"
    assert (audit["action"], audit["outcome"], audit["who"], audit["reason"]) == (
        "activation",
        "activated",
        "admin",
        "json",
    )
    assert (audit["version"], audit["previous_version"]) == (1, 1)
    assert access["logger"] == "service.access" and access["status"] == 200
    # lines outside any request have no id
    start_up = [line for line in json_lines(log.read_text()) if line["logger"] == "uvicorn.error"]
    assert start_up and not any("request_id" in line for line in start_up)


def test_access_log_off(tmp_path: Path, samples: list[Sample]) -> None:
    with LiveServer(tmp_path / "data", log_format="json", access_log="false") as live:
        response = predict(live.client, samples, "quiet-1")
        assert response.headers["X-Request-ID"] == "quiet-1"
        live.client.get("/healthz")
    lines = json_lines(live.log())
    assert lines and not any(line["logger"] == "service.access" for line in lines)
    assert any(line["message"] == "Application shutdown complete." for line in lines)
