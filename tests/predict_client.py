"""Client-side helpers for POST /v1/predict and for reading prediction sets."""

from __future__ import annotations

import json
import math
from typing import Any

import httpx

from tests.samples import Sample, b64


def instances_of(samples: list[Sample]) -> list[dict]:
    return [{"object": s.object, "bbox": s.bbox} for s in samples]


def predict_multipart(
    client: httpx.Client,
    image: bytes,
    parameters: dict[str, Any],
    headers: dict | None = None,
    path: str = "/v1/predict",
) -> httpx.Response:
    files = {
        "image": ("image.jpg", image, "image/jpeg"),
        "request": (None, json.dumps(parameters), "application/json"),
    }
    return client.post(path, files=files, headers=headers or {})


def predict_json(
    client: httpx.Client,
    image: bytes,
    parameters: dict[str, Any],
    headers: dict | None = None,
    path: str = "/v1/predict",
) -> httpx.Response:
    return client.post(path, json={**parameters, "image_base64": b64(image)}, headers=headers or {})


def predict_ok(client: httpx.Client, image: bytes, parameters: dict[str, Any]) -> dict:
    response = predict_json(client, image, parameters)
    assert response.status_code == 200, response.text
    return response.json()


def contains(region: dict, point: tuple[float, float], slack: float = 1e-9) -> bool:
    """Whether ``point`` (image pixels) lies in a set of the response."""
    if region["type"] == "unbounded":
        return True
    dx, dy = point[0] - region["center"][0], point[1] - region["center"][1]
    if region["type"] == "ball":
        return math.hypot(dx, dy) <= region["radius"] * (1 + slack) + slack
    (a, b), (c, d) = region["shape_matrix"]
    return dx * (a * dx + b * dy) + dy * (c * dx + d * dy) <= 1 + slack


def extent(region: dict) -> tuple[float, float]:
    """(smallest, largest) radius of a set; unbounded sets are infinite."""
    if region["type"] == "unbounded":
        return math.inf, math.inf
    if region["type"] == "ball":
        return region["radius"], region["radius"]
    return tuple(region["semi_axes"])  # type: ignore[return-value]
