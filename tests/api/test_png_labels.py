"""The PNG answer to the README's example is legible: every keypoint's label stands clear of the
other labels, the keypoints, the legend and the picture's edges, where the picture shows it."""

from __future__ import annotations

import json
from itertools import combinations

import cv2
import numpy as np

from service.api.predict.predict_schemas import PredictResponse
from service.api.predict.render import layout_labels
from tests.api.in_process import InProcess
from tests.readme import predict_example


def _intersect(a: tuple[int, ...], b: tuple[int, ...]) -> bool:
    return a[0] < b[2] and b[0] < a[2] and a[1] < b[3] and b[1] < a[3]


def test_the_readme_pictures_labels_do_not_overlap(api: InProcess) -> None:
    image, request, _ = predict_example(path="/v1/predict/png")
    files = {"image": (image.name, image.read_bytes(), "image/jpeg"), "request": (None, json.dumps(request))}
    answer = api.client.post("/v1/predict", files=files)
    drawn = api.client.post("/v1/predict/png", files=files)
    assert answer.status_code == drawn.status_code == 200, answer.text
    picture = cv2.imdecode(np.frombuffer(drawn.content, np.uint8), cv2.IMREAD_COLOR)

    labels = layout_labels(picture.shape, PredictResponse.model_validate(answer.json()))
    keypoints = [k for instance in answer.json()["instances"] for k in instance["keypoints"]]
    assert [label.text for label in labels] == [k["name"] for k in keypoints]
    height, width = picture.shape[:2]
    for label in labels:
        x0, y0, x1, y1 = label.box
        assert 0 <= x0 < x1 <= width and 0 <= y0 < y1 <= height, label
        assert (picture[y0, x0] == 0).all() and (picture[y1 - 1, x1 - 1] == 0).all(), "not drawn there"
        for point in (label.keypoint for label in labels):
            assert not (x0 <= point[0] < x1 and y0 <= point[1] < y1), f"{label.text} hides a keypoint"
    overlapping = [(a.text, b.text) for a, b in combinations(labels, 2) if _intersect(a.box, b.box)]
    assert not overlapping
