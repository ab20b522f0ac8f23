"""Camera sequences: one scene, a camera moving a little per frame, labels as for single images."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np
import pytest

from training.coco import ANNOTATIONS_FILENAME
from training.generate import generate
from training.streams import SHIFTS

FRAMES = 3


def _sequence(folder: Path, shift: str = "none") -> dict:
    spec = SHIFTS[shift]
    generate(
        folder,
        1,
        5,
        "stream",
        extra_occluders=spec.extra_occluders,
        frames=FRAMES,
        shift=spec,
        progress=False,
    )
    return json.loads((folder / ANNOTATIONS_FILENAME).read_text())


@pytest.fixture(scope="module")
def sequence(tmp_path_factory: pytest.TempPathFactory) -> tuple[Path, dict]:
    folder = tmp_path_factory.mktemp("stream")
    return folder, _sequence(folder)


def test_a_sequence_is_one_scene_seen_from_a_moving_camera(sequence: tuple[Path, dict]) -> None:
    folder, coco = sequence
    assert [(im["sequence"], im["frame"]) for im in coco["images"]] == [(0, k) for k in range(FRAMES)]
    assert coco["info"]["frames"] == FRAMES and coco["info"]["images"] == FRAMES
    by_frame: dict[int, dict[int, np.ndarray]] = {}
    for ann in coco["annotations"]:
        by_frame.setdefault(ann["image_id"], {})[ann["category_id"]] = np.array(ann["bbox"])
        assert len(ann["keypoints"]) == 3 * 8
    first, last = by_frame[1], by_frame[FRAMES]
    assert first.keys() == last.keys(), "the same objects stay in view"
    moved = [np.abs(last[c] - first[c]).max() for c in first]
    assert 0 < max(moved) < 60, "the camera moves, a little"
    images = [cv2.imread(str(folder / im["file_name"])).astype(float) for im in coco["images"]]
    assert 0 < np.abs(images[1] - images[0]).mean() < 20


def test_shifted_sequences_degrade_the_same_scene(sequence: tuple[Path, dict], tmp_path: Path) -> None:
    folder, coco = sequence
    blurred = _sequence(tmp_path / "blur", "blur")
    assert [a["keypoints"] for a in blurred["annotations"]] == [a["keypoints"] for a in coco["annotations"]]

    def sharpness(root: Path, document: dict) -> float:
        image = cv2.imread(str(root / document["images"][0]["file_name"]), cv2.IMREAD_GRAYSCALE)
        return float(cv2.Laplacian(image, cv2.CV_64F).var())

    assert sharpness(tmp_path / "blur", blurred) < 0.5 * sharpness(folder, coco)


def test_image_only_shifts_need_sequences(tmp_path: Path) -> None:
    with pytest.raises(ValueError, match="sequences"):
        generate(tmp_path, 1, 5, "x", shift=SHIFTS["blur"], progress=False)
