"""The API answers as openapi/openapi.json says: strict inputs, the methods a path serves in
``Allow``, every error a problem+json the document describes (in process, the real app)."""

from __future__ import annotations

import json

import pytest

from service.infra.settings import PACKAGE_ROOT
from tests.api.in_process import InProcess
from tests.service_calls import assert_problem

DOCUMENT = json.loads((PACKAGE_ROOT / "openapi" / "openapi.json").read_text(encoding="utf-8"))
ACTIVATE = "/v1/admin/calibrations/1/activate"


@pytest.mark.parametrize("body", [{"force": 0}, {"force": "yes"}, {"force": True}, {"extra": 1}])
def test_activation_takes_booleans_as_booleans_and_nothing_else(api: InProcess, body: dict) -> None:
    assert_problem(api.client.post(ACTIVATE, json=body, headers=api.admin), 422)


def test_a_body_that_is_not_utf8_is_a_422_problem(api: InProcess) -> None:
    headers = {**api.admin, "Content-Type": "application/json"}
    assert_problem(api.client.post(ACTIVATE, content=b'{"reason": "\xff"}', headers=headers), 422, "UTF-8")


@pytest.mark.parametrize("path", ["/v1/admin/calibrations", "/v1/admin/audits"])
@pytest.mark.parametrize("method", ["OPTIONS", "DELETE", "PUT"])
def test_405_names_every_method_the_path_serves(api: InProcess, path: str, method: str) -> None:
    response = api.client.request(method, path, headers=api.admin)
    assert_problem(response, 405)
    assert response.headers["allow"] == "GET, POST"


def test_audit_epsilons_outside_0_1_are_refused_before_the_upload(api: InProcess) -> None:
    for epsilon in ("0", "1", "-0.1"):
        headers = {**api.admin, "Content-Type": "application/zip"}
        response = api.client.post(
            "/v1/admin/audits", content=b"PK", params={"epsilon": epsilon}, headers=headers
        )
        assert_problem(response, 422, "epsilon")


def test_every_error_the_document_names_is_a_problem_with_the_request_id_header() -> None:
    problem = {"application/problem+json": {"schema": {"$ref": "#/components/schemas/Problem"}}}
    for path, operations in DOCUMENT["paths"].items():
        for method, operation in operations.items():
            where = f"{method.upper()} {path}"
            for status, response in operation["responses"].items():
                assert "X-Request-ID" in response["headers"], (where, status)
                if int(status) >= 400:
                    assert response["content"] == problem, (where, status)
            if path.startswith("/v1/admin"):
                assert {"401", "403", "503"} <= operation["responses"].keys(), where
    assert "HTTPValidationError" not in DOCUMENT["components"]["schemas"]
    assert set(DOCUMENT["components"]["schemas"]["Problem"]["properties"]) >= {
        "type",
        "title",
        "status",
        "detail",
        "errors",
        "request_id",
    }


def test_every_problem_of_a_predict_request_is_in_one_answer(api: InProcess) -> None:
    request = {"instances": [{"object": "no-such-object", "bbox": [1, 1, 10, 10]}], "epsilon": 2}
    body = {**request, "image_base64": "AAAA"}
    problem = assert_problem(api.client.post("/v1/predict", json=body), 422, "epsilon", "no-such-object")
    assert len(problem["errors"]) == 2, problem


def test_a_path_without_v1_points_at_it_and_at_the_docs(api: InProcess) -> None:
    assert_problem(api.client.post("/predict", json={}), 404, "send POST /v1/predict", "/docs")
    assert_problem(api.client.get("/model"), 404, "send GET /v1/model", "/docs")
    problem = assert_problem(api.client.get("/no/such/path"), 404, "/docs")
    assert "/v1/no/such/path" not in problem["detail"], problem


def test_activation_takes_no_body_as_an_empty_one(api: InProcess) -> None:
    """The document gives the body one schema and does not require it."""
    body = DOCUMENT["paths"]["/v1/admin/calibrations/{version}/activate"]["post"]["requestBody"]
    assert body == {
        "content": {"application/json": {"schema": {"$ref": "#/components/schemas/ActivationIn"}}}
    }
    answer = api.client.post(ACTIVATE, headers=api.admin)
    assert answer.status_code == 200, answer.text
    assert answer.json()["version"] == 1


def test_box_sizes_are_refused_where_the_schema_refuses_them(api: InProcess) -> None:
    sizes = DOCUMENT["components"]["schemas"]["InstanceIn"]["properties"]["bbox"]["prefixItems"][2:]
    assert all(size == {"type": "number", "minimum": 1.0} for size in sizes), sizes
    instance = {"object": "duck", "bbox": [4, 4, 0.99, 8]}
    body = {"image_base64": "AAAA", "instances": [instance]}
    assert_problem(api.client.post("/v1/predict", json=body), 422, "at least 1 pixel")
