"""The manifest of the bundled detector, built from the object catalog with the service's schema."""

from __future__ import annotations

import json
from pathlib import Path

from service.detector.manifest import (
    MANIFEST_FILENAME,
    CropSpec,
    HeatmapSpec,
    InputSpec,
    KeypointSpec,
    Manifest,
    ObjectSpec,
    OutputSpec,
)
from training.coco import keypoint_names
from training.keypoints3d import KEYPOINTS_PER_OBJECT, class_keypoints
from training.objects import OBJECT_CLASSES

MODEL_NAME = "lmo-synth-unet"
INPUT_SIZE = 128
HEATMAP_SIZE = 64
IMAGENET_MEAN = (0.485, 0.456, 0.406)
IMAGENET_STD = (0.229, 0.224, 0.225)


def object_channels(class_index: int) -> list[int]:
    """Output channels of one object class: a contiguous slice of 8."""
    start = class_index * KEYPOINTS_PER_OBJECT
    return list(range(start, start + KEYPOINTS_PER_OBJECT))


def build_manifest(name: str = MODEL_NAME, top_k: int = 100) -> Manifest:
    """The manifest; ``top_k`` starts at the paper's 100 and is then chosen per model by
    ``python -m training.select_top_k --write``."""
    keypoints, objects = [], []
    for c, obj in enumerate(OBJECT_CLASSES):
        channels = object_channels(c)
        names = keypoint_names(obj.name)
        keypoints += [
            KeypointSpec(index=i, name=n, object=obj.name) for i, n in zip(channels, names, strict=True)
        ]
        kps_mm = [tuple(round(float(v) * 1000.0, 3) for v in row) for row in class_keypoints(c)]
        objects.append(ObjectSpec(name=obj.name, keypoints=tuple(channels), keypoints_3d=tuple(kps_mm)))
    return Manifest(
        name=name,
        input=InputSpec(
            name="image",
            height=INPUT_SIZE,
            width=INPUT_SIZE,
            color="RGB",
            scale=255.0,
            mean=IMAGENET_MEAN,
            std=IMAGENET_STD,
        ),
        crop=CropSpec(padding=0.25),
        output=OutputSpec(name="heatmaps", height=HEATMAP_SIZE, width=HEATMAP_SIZE),
        heatmap=HeatmapSpec(normalization="anchor", top_k=top_k),
        keypoints=tuple(keypoints),
        objects=tuple(objects),
    )


def write_manifest(model_dir: Path, manifest: Manifest) -> Path:
    path = Path(model_dir) / MANIFEST_FILENAME
    path.write_text(json.dumps(manifest.model_dump(mode="json"), indent=2) + "\n", encoding="utf-8")
    return path
