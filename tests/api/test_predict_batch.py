"""POST /v1/predict/batch in process (the ASGI app): one answer per image, in order, each what
POST /v1/predict would have answered for that image alone; admission counts images."""

from __future__ import annotations

import base64
import json
from typing import Any

import httpx
import pytest

from tests.api.in_process import InProcess
from tests.predict_client import instances_of, predict_multipart
from tests.samples import Sample, samples_by_image
from tests.service_calls import assert_problem

Part = tuple[str, tuple[str | None, bytes, str]]


def image_part(index: int, data: bytes) -> Part:
    return f"image_{index}", ("image.jpg", data, "image/jpeg")


def request_part(index: int, parameters: dict[str, Any] | str) -> Part:
    raw = parameters if isinstance(parameters, str) else json.dumps(parameters)
    return f"request_{index}", (None, raw.encode(), "application/json")


def post_batch(client: httpx.Client, parts: list[Part]) -> httpx.Response:
    return client.post("/v1/predict/batch", files=parts)


def without_request(problem: dict) -> dict:
    """A problem's members but those naming its request (its path, its id)."""
    return {key: value for key, value in problem.items() if key not in ("instance", "request_id")}


@pytest.fixture(scope="module")
def images(samples: list[Sample]) -> list[tuple[bytes, list[dict]]]:
    return [(path.read_bytes(), instances_of(group)) for path, group in samples_by_image(samples).items()]


def test_good_and_bad_images_are_answered_in_order(api: InProcess, images) -> None:
    (first, first_instances), (second, second_instances), (third, third_instances) = images[:3]
    truncated = first[: len(first) // 2] + b"\xff\xd9"
    singles = [  # (image, request) as POST /v1/predict takes them; None where a part is left out
        (first, {"instances": first_instances}),
        (truncated, {"instances": first_instances}),
        (second, {"instances": second_instances, "nonconformity": "var", "epsilon": 0.2}),
        (second, {"instances": []}),
        (third, {"instances": [{"object": "no-such-object", "bbox": [10, 10, 20, 20]}]}),
        (b"GIF89a not a JPEG", {"instances": first_instances}),
        (third, {"instances": third_instances, "nonconformity": "peak", "coverage": "object"}),
    ]
    parts = [p for i, (image, r) in enumerate(singles) for p in (image_part(i, image), request_part(i, r))]

    response = post_batch(api.client, parts)
    assert response.status_code == 200, response.text
    items = response.json()["items"]
    assert len(items) == len(singles)

    for index, (item, (image, parameters)) in enumerate(zip(items, singles, strict=True)):
        alone = predict_multipart(api.client, image, parameters)
        if alone.status_code == 200:
            assert item == {"status": 200, "result": alone.json()}, index
        else:
            problem = alone.json()
            assert item["status"] == alone.status_code == problem["status"], (index, item)
            assert item["problem"]["instance"] == "/v1/predict/batch"
            assert without_request(item["problem"]) == without_request(problem), index
    assert [item["status"] for item in items] == [200, 422, 200, 422, 422, 415, 200]


def test_a_json_batch_is_answered_as_its_multipart_twin(api: InProcess, images) -> None:
    (first, first_instances), (second, second_instances), (third, _) = images[:3]
    requests = [
        {"instances": first_instances},
        {"instances": second_instances, "nonconformity": "var", "epsilon": 0.2},
        {"instances": [{"object": "no-such-object", "bbox": [10, 10, 20, 20]}]},
    ]
    pictures = [first, second, third]
    parts = [
        p
        for i, (image, r) in enumerate(zip(pictures, requests, strict=True))
        for p in (image_part(i, image), request_part(i, r))
    ]
    as_json = {
        "items": [
            {"image_base64": base64.b64encode(image).decode(), **r}
            for image, r in zip(pictures, requests, strict=True)
        ]
    }
    multipart, json_body = (
        post_batch(api.client, parts).json(),
        api.client.post("/v1/predict/batch", json=as_json).json(),
    )
    for item in (*multipart["items"], *json_body["items"]):
        item.get("problem", {}).pop("request_id", None)
    assert [item["status"] for item in json_body["items"]] == [200, 200, 422]
    assert json_body == multipart
    broken = {"items": [as_json["items"][0], {"image_base64": "@@", **requests[0]}, {"instances": []}]}
    statuses = [item["status"] for item in api.client.post("/v1/predict/batch", json=broken).json()["items"]]
    assert statuses == [200, 422, 422]


def test_a_malformed_batch_is_refused_whole(api: InProcess, images) -> None:
    image, instances = images[0]
    good = [image_part(0, image), request_part(0, {"instances": instances})]
    text_body = api.client.post("/v1/predict/batch", content=b"hello", headers={"Content-Type": "text/plain"})
    assert_problem(text_body, 415, "multipart/form-data", "image_0", "application/json")
    assert_problem(api.client.post("/v1/predict/batch", json={"instances": instances}), 422, '{"items"')
    assert_problem(api.client.post("/v1/predict/batch", json={"items": []}), 422, "the batch is empty")
    too_many = {"items": [{"image_base64": "AA==", "instances": instances}] * 17}
    assert_problem(api.client.post("/v1/predict/batch", json=too_many), 422, "at most 16 images")
    assert_problem(
        post_batch(api.client, [*good, ("picture_1", ("a.jpg", image, "image/jpeg"))]),
        422,
        "unexpected part 'picture_1'",
    )
    assert_problem(
        post_batch(api.client, [*good, image_part(16, image), request_part(16, {})]),
        422,
        "at most 16 images",
    )
    assert_problem(
        post_batch(api.client, [*good, image_part(0, image)]), 422, "'image_0' appears more than once"
    )
    request = request_part(2, {"instances": instances})
    gaps = post_batch(api.client, [image_part(0, image), image_part(2, image), request])
    assert_problem(gaps, 422, "'request_0' is missing", "'image_1' is missing", "'request_1' is missing")
    empty = api.client.post(
        "/v1/predict/batch",
        content=b"--edge--\r\n",
        headers={"Content-Type": "multipart/form-data; boundary=edge"},
    )
    assert_problem(empty, 422, "the batch is empty")
    assert post_batch(api.client, good).status_code == 200


def test_a_json_batch_is_answered_the_same_in_any_spelling_json_allows(api: InProcess, images) -> None:
    """Items read straight from the body (UTF-8) and bodies read whole first (UTF-16, a BOM, an
    item's JSON broken) answer alike: escapes, spacing, a bracket or an escaped quote in a string,
    a repeated member (the last counts)."""
    image, instances = images[0]
    item = {"image_base64": base64.b64encode(image).decode(), "instances": instances}
    plain = json.dumps({"items": [item, {**item, "epsilon": 2}]})
    name = instances[0]["object"]
    spelled = (
        plain.replace(f'"{name}"', '"' + "".join(f"\\u{ord(c):04x}" for c in name) + '"'),
        plain.replace(", ", " ,\n\t").replace("{", "{ \r\n"),
        plain.replace('"epsilon": 2', '"epsilon": 0.5, "stream": "]\\"}", "epsilon": 2, "stream": null'),
    )

    def answer(body: bytes) -> list:
        response = api.client.post(
            "/v1/predict/batch", content=body, headers={"Content-Type": "application/json"}
        )
        items = response.json()["items"]
        return [
            {**one, "problem": without_request(one["problem"])} if "problem" in one else one for one in items
        ]

    expected = answer(plain.encode())
    assert [one["status"] for one in expected] == [200, 422]
    for body in (
        *(text.encode() for text in spelled),
        plain.encode("utf-16"),
        b"\xef\xbb\xbf" + plain.encode(),
    ):
        assert answer(body) == expected, body[:80]
    broken = plain.replace('"instances"', '"stream": "\\ud800", "instances"', 1).encode()
    refused, kept = answer(broken)  # a lone surrogate: read whole, the item written again, refused
    assert (refused["status"], kept) == (422, expected[1])
    assert "is not valid JSON (unexpected end of hex escape" in refused["problem"]["detail"], refused
