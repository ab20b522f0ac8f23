"""The COCO keypoints layout shared by the generator, training, evaluation and the service."""

from __future__ import annotations

import json
from pathlib import Path

from training.keypoints3d import KEYPOINTS_PER_OBJECT
from training.objects import OBJECT_CLASSES

ANNOTATIONS_FILENAME = "annotations.json"


def keypoint_names(object_name: str) -> list[str]:
    return [f"{object_name}_kp{k}" for k in range(KEYPOINTS_PER_OBJECT)]


def categories() -> list[dict]:
    """One category per object class, ids 1..C in manifest order."""
    return [
        {
            "id": i + 1,
            "name": obj.name,
            "supercategory": "object",
            "keypoints": keypoint_names(obj.name),
            "skeleton": [],
        }
        for i, obj in enumerate(OBJECT_CLASSES)
    ]


def write_coco(path: Path, images: list[dict], annotations: list[dict], info: dict) -> None:
    doc = {"info": info, "images": images, "annotations": annotations, "categories": categories()}
    tmp = path.with_suffix(".tmp")
    tmp.write_text(json.dumps(doc), encoding="utf-8")
    tmp.replace(path)


def read_coco(path: Path) -> dict:
    return json.loads(Path(path).read_text(encoding="utf-8"))
