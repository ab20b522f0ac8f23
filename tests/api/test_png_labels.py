"""The PNG answer to the README's example is legible: every keypoint's label stands clear of the
other labels, the keypoints, the legend and the picture's edges, where the picture shows it, and
its text meets WCAG AA contrast (4.5:1) against its box."""

from __future__ import annotations

import json
from itertools import combinations

import cv2
import numpy as np
import pytest

from service.api.predict.predict_schemas import PredictResponse
from service.api.predict.render import Label, layout_labels
from tests.api.in_process import InProcess
from tests.readme import predict_example


def _intersect(a: tuple[int, ...], b: tuple[int, ...]) -> bool:
    return a[0] < b[2] and b[0] < a[2] and a[1] < b[3] and b[1] < a[3]


def _relative_luminance(bgr: np.ndarray) -> float:
    """WCAG 2.x relative luminance of an 8-bit sRGB colour (OpenCV's BGR order)."""
    channel = bgr[::-1] / 255.0
    linear = np.where(channel <= 0.03928, channel / 12.92, ((channel + 0.055) / 1.055) ** 2.4)
    return float(linear @ [0.2126, 0.7152, 0.0722])


def contrast_ratio(a: np.ndarray, b: np.ndarray) -> float:
    lighter, darker = sorted((_relative_luminance(a), _relative_luminance(b)), reverse=True)
    return (lighter + 0.05) / (darker + 0.05)


def test_contrast_ratio_is_wcags() -> None:
    white, black = np.array([255, 255, 255]), np.array([0, 0, 0])
    assert contrast_ratio(white, black) == pytest.approx(21)
    assert contrast_ratio(np.array([118, 118, 118]), white) == pytest.approx(4.54, abs=0.01)  # #767676


@pytest.fixture(scope="module")
def readme_picture(api: InProcess) -> tuple[np.ndarray, list[Label], list[dict]]:
    """The README's PNG example, drawn; its labels and its keypoints."""
    image, request, _ = predict_example(path="/v1/predict/png")
    files = {"image": (image.name, image.read_bytes(), "image/jpeg"), "request": (None, json.dumps(request))}
    answer = api.client.post("/v1/predict", files=files)
    drawn = api.client.post("/v1/predict/png", files=files)
    assert answer.status_code == drawn.status_code == 200, answer.text
    picture = cv2.imdecode(np.frombuffer(drawn.content, np.uint8), cv2.IMREAD_COLOR)
    labels = layout_labels(picture.shape, PredictResponse.model_validate(answer.json()))
    keypoints = [k for instance in answer.json()["instances"] for k in instance["keypoints"]]
    return picture, labels, keypoints


def test_every_label_meets_wcag_aa_contrast_on_its_box(
    readme_picture: tuple[np.ndarray, list[Label], list[dict]],
) -> None:
    picture, labels, _ = readme_picture
    assert len({label.colour for label in labels}) > 1  # the palette, not one colour
    for label in labels:
        x0, y0, x1, y1 = label.box
        inside = picture[y0:y1, x0:x1].reshape(-1, 3)
        background = picture[y0, x0]
        text = inside[(inside == label.colour).all(axis=1)]
        assert len(text), f"{label.text}: no pixel of its colour {label.colour} in its box"
        ratio = contrast_ratio(text[0].astype(float), background.astype(float))
        assert ratio >= 4.5, f"{label.text}: {label.colour} on {background.tolist()} is {ratio:.2f}:1"


def test_the_readme_pictures_labels_do_not_overlap(
    readme_picture: tuple[np.ndarray, list[Label], list[dict]],
) -> None:
    picture, labels, keypoints = readme_picture
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
