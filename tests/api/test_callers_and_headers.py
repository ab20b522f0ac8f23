"""Who a predict request is (a predict token's holder where predict tokens are on, else an address),
and request headers bounded in count and size (431)."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import pytest

from tests.api.in_process import InProcess
from tests.predict_client import predict_json
from tests.service_calls import ADMIN_TOKEN, assert_problem

PREDICT_TOKEN = "robot-7-predict-token-0123456789"
FEEDBACK_TOKEN = "labeller-feedback-token-0123456789"


@pytest.fixture(scope="module")
def tokens_on(tmp_path_factory: pytest.TempPathFactory) -> Iterator[InProcess]:
    folder = tmp_path_factory.mktemp("tokens")
    tokens = folder / "tokens"
    tokens.write_text(f"predict robot-7:{PREDICT_TOKEN}\nfeedback labeller:{FEEDBACK_TOKEN}\n")
    with InProcess(folder / "data", admin_token=ADMIN_TOKEN, admin_tokens_file=str(tokens)) as service:
        yield service


def _bearer(token: str) -> dict[str, str]:
    return {"Authorization": f"Bearer {token}"}


def test_with_predict_tokens_a_request_without_one_gets_401(
    tokens_on: InProcess, sample: tuple[bytes, list[dict]]
) -> None:
    image, instances = sample
    for headers in ({}, _bearer("not-a-token-of-this-service"), _bearer(FEEDBACK_TOKEN)):
        response = predict_json(tokens_on.client, image, {"instances": instances}, headers=headers)
        problem = assert_problem(response, 401, "'predict name:token' line of CKS_ADMIN_TOKENS_FILE")
        assert response.headers["www-authenticate"] == "Bearer", problem


def test_a_predict_or_admin_token_predicts(tokens_on: InProcess, sample: tuple[bytes, list[dict]]) -> None:
    image, instances = sample
    for token in (PREDICT_TOKEN, ADMIN_TOKEN):
        response = predict_json(tokens_on.client, image, {"instances": instances}, headers=_bearer(token))
        assert response.status_code == 200, response.text


def test_a_predict_token_is_not_an_admin_token(tokens_on: InProcess) -> None:
    response = tokens_on.client.get("/v1/admin/calibrations", headers=_bearer(PREDICT_TOKEN))
    assert_problem(response, 401, "not an admin token")


def test_without_predict_tokens_predict_needs_none(api: InProcess, sample: tuple[bytes, list[dict]]) -> None:
    image, instances = sample
    assert predict_json(api.client, image, {"instances": instances}).status_code == 200


@pytest.mark.parametrize(
    "headers",
    [{"X-Big": "a" * 1_000_000}, {f"X-Many-{i}": "1" for i in range(20_000)}],
    ids=["a 1 MB header", "20,000 headers"],
)
def test_headers_over_the_limit_get_431(api: InProcess, headers: dict[str, str]) -> None:
    response = api.client.get("/healthz", headers=headers)
    assert_problem(response, 431, "at most 100 headers of 16384 bytes")


def test_headers_within_the_limit_pass(api: InProcess) -> None:
    headers = {f"X-Fine-{i}": "b" * 100 for i in range(90)}
    assert api.client.get("/healthz", headers=headers).status_code == 200


def test_predict_tokens_are_on_while_the_tokens_file_has_a_predict_line(tmp_path: Path) -> None:
    tokens = tmp_path / "tokens"
    tokens.write_text(f"predict robot-7:{PREDICT_TOKEN}\n")
    with InProcess(tmp_path / "data", admin_tokens_file=str(tokens)) as service:
        assert service.client.post("/v1/predict", json={}).status_code == 401
    tokens.write_text(f"admin:{ADMIN_TOKEN}\n")  # predict tokens off again: predict needs none
    with InProcess(tmp_path / "data", admin_tokens_file=str(tokens)) as service:
        assert service.client.post("/v1/predict", json={}).status_code == 422
