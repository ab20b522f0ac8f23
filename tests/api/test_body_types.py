"""Bodies as client generators send them (issue 38), in process: one request content type per
documented operation, the multipart forms on their own paths (the old paths still take them), a
JSON part with or without a filename and of any JSON type, and a raw zip judged by its bytes."""

from __future__ import annotations

import base64
import json
from pathlib import Path
from typing import Any

import jsonschema
import pytest

from service.infra.settings import PACKAGE_ROOT
from tests.api.in_process import InProcess
from tests.predict_client import instances_of, predict_json, predict_multipart
from tests.samples import Sample, batch_zip, samples_by_image
from tests.service_calls import assert_problem

DOCUMENT = json.loads((PACKAGE_ROOT / "openapi" / "openapi.json").read_text(encoding="utf-8"))
FORMS = {  # each form's own path: the JSON or raw operation's path + /form
    "/v1/predict": "/v1/predict/form",
    "/v1/predict/png": "/v1/predict/png/form",
    "/v1/predict/batch": "/v1/predict/batch/form",
    "/v1/admin/calibrations": "/v1/admin/forms/calibrations",
    "/v1/admin/audits": "/v1/admin/forms/audits",
}
AGAIN = {"allow_duplicate": "true", "reason": "the same samples again, sent another way"}


@pytest.fixture(scope="module")
def sample(samples: list[Sample]) -> tuple[bytes, dict[str, Any]]:
    path, group = next(iter(samples_by_image(samples).items()))
    return path.read_bytes(), {"instances": instances_of(group)}


def test_every_operation_documents_one_request_content_type() -> None:
    types = {
        f"{method.upper()} {path}": list(operation["requestBody"]["content"])
        for path, operations in DOCUMENT["paths"].items()
        for method, operation in operations.items()
        if "requestBody" in operation
    }
    assert all(len(kinds) == 1 for kinds in types.values()), types
    for path, form in FORMS.items():
        assert types[f"POST {form}"] == ["multipart/form-data"], form
        assert types[f"POST {path}"] != ["multipart/form-data"], path


def test_the_documented_objects_are_the_models(api: InProcess) -> None:
    served = api.client.get("/openapi.json").json()["components"]["schemas"]["InstanceIn"]
    names = [o["name"] for o in api.client.get("/v1/model").json()["manifest"]["objects"]]
    assert served["properties"]["object"]["enum"] == names


@pytest.mark.parametrize("path", ["/v1/predict", "/v1/predict/form"])
def test_both_bodies_answer_alike_on_either_path(api: InProcess, sample, path: str) -> None:
    image, parameters = sample
    as_json = predict_json(api.client, image, parameters, path=path)
    as_form = predict_multipart(api.client, image, parameters, path=path)
    assert as_json.status_code == as_form.status_code == 200, as_form.text
    assert as_json.json() == as_form.json()


@pytest.mark.parametrize(
    "json_type",
    ["application/json", "application/json; charset=utf-8", "text/plain", "application/octet-stream", ""],
)
@pytest.mark.parametrize("filename", [None, "blob"])
def test_the_json_part_is_taken_with_or_without_a_filename(
    api: InProcess, sample, json_type: str, filename: str | None
) -> None:
    image, parameters = sample
    expected = predict_json(api.client, image, parameters).json()
    for path in ("/v1/predict/form", "/v1/predict/png/form"):
        files = {
            "image": ("image.jpg", image, "image/jpeg"),
            "request": (filename, json.dumps(parameters).encode(), json_type or None),
        }
        response = api.client.post(path, files=files)
        assert response.status_code == 200, response.text
        if path == "/v1/predict/form":
            assert response.json() == expected


def test_batch_requests_as_files(api: InProcess, sample) -> None:
    image, parameters = sample
    raw = json.dumps(parameters).encode()
    parts = [
        ("image_0", ("a.jpg", image, "image/jpeg")),
        ("request_0", ("blob", raw, "application/json")),
        ("image_1", ("b.jpg", image, "image/jpeg")),
        ("request_1", (None, raw, "application/json")),
    ]
    response = api.client.post("/v1/predict/batch/form", files=parts)
    assert response.status_code == 200, response.text
    assert [item["status"] for item in response.json()["items"]] == [200, 200]


@pytest.mark.parametrize(
    ("parts", "fragments"),
    [
        ({"extra": (None, b"x")}, ["unexpected multipart part 'extra'", "image", "request"]),
        ({"image2": ("c.jpg", b"\xff", "image/jpeg"), "x": ("d", b"1")}, ["too many parts", "image"]),
    ],
)
def test_a_wrong_form_has_one_wording_and_no_400(api: InProcess, sample, parts: dict, fragments) -> None:
    image, parameters = sample
    files = [
        ("image", ("image.jpg", image, "image/jpeg")),
        ("request", ("blob", json.dumps(parameters).encode(), "application/json")),
        *parts.items(),
    ]
    body = assert_problem(api.client.post("/v1/predict/form", files=files), 422, *fragments)
    assert "400" not in body["detail"], body


def test_a_repeated_part_and_an_image_sent_as_a_field_are_named(api: InProcess, sample) -> None:
    image, parameters = sample
    raw = json.dumps(parameters).encode()
    twice = [("image", ("a.jpg", image, "image/jpeg"))] * 2 + [("request", (None, raw))]
    assert_problem(api.client.post("/v1/predict/form", files=twice), 422, "'image' appears more than once")
    as_field = [("image", (None, b"not a file")), ("request", (None, raw))]
    assert_problem(api.client.post("/v1/predict/form", files=as_field), 422, "'image' must be a file")


@pytest.mark.parametrize("content_type", [None, "text/plain", "application/octet-stream", "application/json"])
@pytest.mark.parametrize("path", ["/v1/admin/calibrations", "/v1/admin/forms/calibrations"])
def test_a_raw_zip_is_judged_by_its_bytes(
    api: InProcess, samples_dir: Path, coco: dict, content_type: str | None, path: str
) -> None:
    headers = {**api.admin, **({} if content_type is None else {"Content-Type": content_type})}
    zipped = batch_zip(samples_dir, coco, images=2)
    accepted = api.client.post(path, content=zipped, headers=headers, params=AGAIN)
    assert accepted.status_code == 202, accepted.text
    assert_problem(api.client.post(path, content=b"not a zip", headers=headers), 422, "zip")


@pytest.mark.parametrize("path", ["/v1/admin/forms/audits", "/v1/admin/forms/calibrations"])
def test_the_forms_own_paths_take_the_zip_as_its_part(
    api: InProcess, samples_dir: Path, coco: dict, path: str
) -> None:
    files = {"file": ("batch.zip", batch_zip(samples_dir, coco, images=2), "application/zip")}
    response = api.client.post(path, files=files, headers=api.admin, params=AGAIN)
    assert response.status_code == 202, response.text
    assert response.headers["location"] == f"/v1/admin/jobs/{response.json()['id']}"


def test_the_overrides_rule_is_in_the_schema_and_the_server_keeps_it(api: InProcess) -> None:
    """force and allow_duplicate need a non-blank reason: the document's schema refuses what the
    server refuses, and accepts what it takes (on either upload operation)."""
    for path in ("/v1/admin/calibrations", "/v1/admin/forms/calibrations"):
        parameters = DOCUMENT["paths"][path]["post"]["parameters"]
        (overrides,) = [p for p in parameters if p["name"] == "overrides"]
        assert (overrides["in"], overrides["style"], overrides["explode"]) == ("query", "form", True)
        rule = jsonschema.Draft202012Validator(overrides["schema"])
        for query, allowed in [
            ({"force": True}, False),
            ({"allow_duplicate": True, "reason": " "}, False),
            ({"force": True, "reason": "why"}, True),
            ({"reason": ""}, True),
        ]:
            assert rule.is_valid(query) is allowed, query
            sent = {k: str(v).lower() if isinstance(v, bool) else v for k, v in query.items()}
            params = {**sent, "activate": "true"}  # force applies to activating only (said in prose)
            answer = api.client.post(path, content=b"PK", params=params, headers=api.admin)
            if allowed:
                assert_problem(answer, 422, "zip")  # past the overrides, refused for its body
            else:
                assert_problem(answer, 422, "needs a reason")


def test_a_batch_item_the_schema_would_refuse_is_answered_alone(api: InProcess, sample) -> None:
    """The document declares what a client must send; refusing anything else is behaviour."""
    items = DOCUMENT["components"]["schemas"]["BatchJson"]["properties"]["items"]["items"]
    assert items == {"$ref": "#/components/schemas/PredictJson"}
    image, parameters = sample
    good = {**parameters, "image_base64": base64.b64encode(image).decode()}
    answer = api.client.post("/v1/predict/batch", json={"items": [good, {"epsilon": 2}, "text"]})
    assert answer.status_code == 200, answer.text
    assert [item["status"] for item in answer.json()["items"]] == [200, 422, 422]


@pytest.mark.parametrize(
    "form", ["/v1/admin/forms/calibrations", "/v1/admin/forms/audits", "/v1/predict/form"]
)
def test_a_forms_path_allows_post_only(api: InProcess, form: str) -> None:
    """/v1/admin/forms/calibrations is its own resource, not a version: Allow names POST alone."""
    response = api.client.request("OPTIONS", form, headers=api.admin)
    assert_problem(response, 405)
    assert response.headers["allow"] == "POST"
