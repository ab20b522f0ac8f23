"""Calibration stores each instance's label-free heatmap features, computed exactly as
prediction computes them, and the caller's group labels."""

from __future__ import annotations

import json
import shutil
from pathlib import Path

import numpy as np
import pytest

from service.calibration.bundle import load_bundle
from service.calibration.coco import load_coco_batch
from service.calibration.scoring import ScoreAccumulator, score_batch
from service.conformal import HEATMAP_FEATURES, heatmap_features
from service.detector.images import decode_image
from service.detector.session import Detector
from service.errors import InvalidInput
from service.prediction import calibrated_sets

MODEL_DIR = Path(__file__).resolve().parents[3] / "models" / "lmo-synth-unet"
SAMPLES = MODEL_DIR / "samples"


@pytest.fixture(scope="module")
def detector() -> Detector:
    return Detector(MODEL_DIR, 1)


def _samples_with_groups(tmp_path: Path, groups: dict[int, object]) -> Path:
    folder = tmp_path / "batch"
    shutil.copytree(SAMPLES, folder)
    annotations = json.loads((folder / "annotations.json").read_text())
    for entry in annotations["annotations"]:
        if entry["id"] in groups:
            entry["group"] = groups[entry["id"]]
    (folder / "annotations.json").write_text(json.dumps(annotations))
    return folder


def test_calibration_features_equal_prediction_features(detector: Detector, tmp_path: Path) -> None:
    batch = load_coco_batch(SAMPLES, detector.manifest)
    accumulator = ScoreAccumulator()
    score_batch(batch, "samples", detector, accumulator, max_image_pixels=10**9)
    table = accumulator.table()
    checked = 0
    for image_id, instances in batch.instances_by_image().items():
        image = decode_image(batch.images[image_id].path.read_bytes(), 10**9)
        for instance in instances:
            result = detector.infer(image, instance.bbox[None, :], [instance.object_name])
            sets = calibrated_sets(
                result,
                "cov",
                np.ones(len(detector.manifest.keypoints)),
                detector.manifest.heatmap,
                all_statistics=True,
            )
            live = heatmap_features(sets.statistics)
            block = table.object(instance.object_name)
            row = block.instance_refs.index(f"samples:{image_id}:{instance.annotation_id}")
            for name in HEATMAP_FEATURES:
                np.testing.assert_allclose(block.features[name][row], live[name], rtol=1e-12)
            checked += 1
    assert checked == len(batch.instances) > 0


def test_group_labels_reach_the_score_table(detector: Detector, tmp_path: Path) -> None:
    first = json.loads((SAMPLES / "annotations.json").read_text())["annotations"][0]["id"]
    batch = load_coco_batch(_samples_with_groups(tmp_path, {first: "camera-3"}), detector.manifest)
    accumulator = ScoreAccumulator()
    score_batch(batch, "samples", detector, accumulator, max_image_pixels=10**9)
    labels = [
        (ref, group)
        for block in accumulator.table().objects
        for ref, group in zip(block.instance_refs, block.groups or [""] * block.n_instances, strict=True)
        if group
    ]
    assert len(labels) == 1 and labels[0][1] == "camera-3" and labels[0][0].endswith(f":{first}")


@pytest.mark.parametrize("bad", [3, "", "x" * 65, "caf\u00e9"])
def test_bad_group_labels_are_refused_with_the_annotation_named(
    detector: Detector, tmp_path: Path, bad: object
) -> None:
    first = json.loads((SAMPLES / "annotations.json").read_text())["annotations"][0]["id"]
    with pytest.raises(InvalidInput) as refused:
        load_coco_batch(_samples_with_groups(tmp_path, {first: bad}), detector.manifest)
    assert "group must be 1-64 printable ASCII characters" in str(refused.value.detail)


def test_bundled_calibration_carries_features_of_every_keypoint() -> None:
    _, table = load_bundle(MODEL_DIR / "default_calibration.npz")
    for block in table.objects:
        assert sorted(block.features) == sorted(HEATMAP_FEATURES)
        assert np.isfinite(block.features["gamma"]).all()
        assert (block.features["anisotropy"] >= 1.0).all()
        assert ((block.features["peak_probability"] > 0) & (block.features["peak_probability"] <= 1)).all()
