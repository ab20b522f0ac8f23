"""Extreme epsilon and delta in process (the ASGI app): 200 (maybe with unbounded sets) or 422, never 500.

Issue 12 item 5: a delta with epsilon <= 5.5e-17 answered 500. Values inside (0, 1) are
answered, subnormals and the neighbours of 0 and 1 included; values outside, written as
JSON numbers (1e309 overflows to infinity in a parser), are refused with a 422 problem.
"""

from __future__ import annotations

import itertools
import json
import math

import pytest

from tests.api.in_process import InProcess
from tests.predict_client import instances_of
from tests.samples import Sample, b64, samples_by_image
from tests.service_calls import assert_problem

INSIDE = ("5e-324", "2.2e-308", "5.5e-17", "1e-16", "0.9999999999999999", "0.5")  # 0.99..9 is 1 - 2**-53
OUTSIDE = ("0", "1", "-0.0", "1e309", "-1e309", "1.0000000000000002", "-5e-324", "NaN", "Infinity")


@pytest.fixture(scope="module")
def request_parts(samples: list[Sample]) -> tuple[bytes, list[dict]]:
    """One sample image and its labeled instances."""
    path, group = next(iter(samples_by_image(samples).items()))
    return path.read_bytes(), instances_of(group)


def post(api: InProcess, parts: tuple[bytes, list[dict]], options: dict[str, str]):
    """POST JSON whose option values are written verbatim (so 1e309 stays a JSON number)."""
    image, instances = parts
    fields = [f'"image_base64": "{b64(image)}"', f'"instances": {json.dumps(instances)}']
    fields += [f'"{name}": {text}' for name, text in options.items()]
    body = "{" + ", ".join(fields) + "}"
    return api.client.post("/v1/predict", content=body, headers={"Content-Type": "application/json"})


def strict_json(text: str) -> dict:
    """Parse a response, refusing the non-standard NaN / Infinity tokens."""

    def refuse(token: str) -> None:
        raise AssertionError(f"the response contains {token}")

    return json.loads(text, parse_constant=refuse)


def check_answer(body: dict, epsilon: float, delta: float | None) -> list[dict]:
    """Every guarantee finite and in [0, 1], every set finite or unbounded; returns the keypoints."""
    keypoints = [kp for instance in body["instances"] for kp in instance["keypoints"]]
    assert keypoints
    for keypoint in keypoints:
        guarantee = keypoint["guarantee"]
        assert guarantee["epsilon"] == epsilon and guarantee["delta"] == delta
        assert 0 <= guarantee["t"] <= guarantee["n"]
        bounds = [guarantee["coverage_lower_bound"], guarantee["coverage_upper_bound"]]
        if delta is not None:
            bounds.append(guarantee["pac_failure_probability"])
            assert guarantee["pac_failure_probability"] <= delta
        assert all(math.isfinite(v) and 0.0 <= v <= 1.0 for v in bounds), guarantee
        region = keypoint["set"]
        assert (region["type"] == "unbounded") == (guarantee["t"] == 0), keypoint
        numbers = [v for v in _flatten(region) if not isinstance(v, str)]
        assert all(math.isfinite(v) for v in numbers), region
    return keypoints


def _flatten(value: object) -> list:
    if isinstance(value, dict):
        return [x for v in value.values() for x in _flatten(v)]
    if isinstance(value, list):
        return [x for v in value for x in _flatten(v)]
    return [value]


@pytest.mark.parametrize("nonconformity", ["peak", "cov"])
@pytest.mark.parametrize("coverage", ["keypoint", "object"])
def test_every_epsilon_and_delta_inside_the_interval_is_answered(
    api: InProcess, request_parts: tuple[bytes, list[dict]], nonconformity: str, coverage: str
) -> None:
    for epsilon, delta in itertools.product(INSIDE, (None, *INSIDE)):
        options = {"epsilon": epsilon, "nonconformity": f'"{nonconformity}"', "coverage": f'"{coverage}"'}
        if delta is not None:
            options["delta"] = delta
        response = post(api, request_parts, options)
        assert response.status_code == 200, (options, response.text)
        keypoints = check_answer(
            strict_json(response.text), float(epsilon), None if delta is None else float(delta)
        )
        if float(epsilon) <= 1e-16:  # (n + 1) eps < 1 for any stored n: no finite set is valid
            assert all(kp["set"]["type"] == "unbounded" for kp in keypoints)
        if epsilon == "0.9999999999999999" and delta is None:  # t = n: the smallest score, finite
            assert all(kp["set"]["type"] != "unbounded" for kp in keypoints)


def test_the_issue_12_request(api: InProcess, request_parts: tuple[bytes, list[dict]]) -> None:
    """epsilon = 5.5e-17 with a delta answered 500: now every set is unbounded."""
    response = post(api, request_parts, {"epsilon": "5.5e-17", "delta": "0.1"})
    assert response.status_code == 200, response.text
    keypoints = check_answer(strict_json(response.text), 5.5e-17, 0.1)
    assert {kp["set"]["type"] for kp in keypoints} == {"unbounded"}


@pytest.mark.parametrize("name", ["epsilon", "delta"])
@pytest.mark.parametrize("text", OUTSIDE)
def test_values_outside_the_interval_are_422(
    api: InProcess, request_parts: tuple[bytes, list[dict]], name: str, text: str
) -> None:
    response = post(api, request_parts, {name: text})
    assert_problem(response, 422)
    if text not in ("NaN", "Infinity"):  # not JSON at all: the parser's message names the position
        assert_problem(response, 422, name)


@pytest.mark.parametrize(("epsilon", "delta"), [("5e-324", "5e-324"), ("0.9999999999999999", None)])
def test_multipart_and_png_rendering_answer_too(
    api: InProcess, request_parts: tuple[bytes, list[dict]], epsilon: str, delta: str | None
) -> None:
    image, instances = request_parts
    options = f'"epsilon": {epsilon}' + ("" if delta is None else f', "delta": {delta}')
    files = {
        "image": ("image.jpg", image, "image/jpeg"),
        "request": (None, f'{{"instances": {json.dumps(instances)}, {options}}}', "application/json"),
    }
    response = api.client.post("/v1/predict", files=files)
    assert response.status_code == 200, response.text
    check_answer(strict_json(response.text), float(epsilon), None if delta is None else float(delta))
    rendered = api.client.post("/v1/predict", files=files, headers={"Accept": "image/png"})
    assert rendered.status_code == 200, rendered.text
    assert rendered.headers["content-type"] == "image/png" and rendered.content.startswith(b"\x89PNG")
