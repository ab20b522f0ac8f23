"""The synthetic data generator: COCO structure, visibility flags, labels, determinism."""

from __future__ import annotations

import json
from pathlib import Path

import cv2
import numpy as np

from tests.unit.training.conftest import TINY_IMAGES, TINY_SEED
from training.coco import ANNOTATIONS_FILENAME
from training.generate import generate
from training.manifest import build_manifest


def _coco(folder: Path) -> dict:
    return json.loads((folder / ANNOTATIONS_FILENAME).read_text())


def test_coco_structure(tiny_split: Path) -> None:
    coco = _coco(tiny_split)
    manifest = build_manifest()
    assert len(coco["images"]) == TINY_IMAGES
    assert [c["name"] for c in coco["categories"]] == list(manifest.object_names)
    for cat in coco["categories"]:
        channels = manifest.object(cat["name"]).keypoints
        assert cat["keypoints"] == [manifest.keypoints[i].name for i in channels]
    for im in coco["images"]:
        image = cv2.imread(str(tiny_split / im["file_name"]))
        assert image.shape == (im["height"], im["width"], 3)
    assert coco["annotations"], "the fixed seed should give annotated objects"
    for ann in coco["annotations"]:
        assert {
            "bbox",
            "keypoints",
            "num_keypoints",
            "area",
            "iscrowd",
            "visib_fract",
            "cam_K",
            "cam_R_m2c",
            "cam_t_m2c",
        } <= set(ann)
        assert len(ann["keypoints"]) == 3 * 8 and ann["num_keypoints"] == 8
        rot = np.array(ann["cam_R_m2c"])
        np.testing.assert_allclose(rot @ rot.T, np.eye(3), atol=1e-9)
        assert 0.0 < ann["visib_fract"] <= 1.0


def test_boxes_and_visible_labels_inside_image(tiny_split: Path) -> None:
    coco = _coco(tiny_split)
    sizes = {im["id"]: (im["width"], im["height"]) for im in coco["images"]}
    flags = []
    for ann in coco["annotations"]:
        w, h = sizes[ann["image_id"]]
        x, y, bw, bh = ann["bbox"]
        assert x >= 0 and y >= 0 and x + bw <= w + 1e-6 and y + bh <= h + 1e-6 and min(bw, bh) >= 20
        kps = np.array(ann["keypoints"]).reshape(-1, 3)
        assert set(kps[:, 2].tolist()) <= {1, 2}
        visible = kps[kps[:, 2] == 2]
        assert ((visible[:, 0] >= 0) & (visible[:, 0] < w) & (visible[:, 1] >= 0) & (visible[:, 1] < h)).all()
        flags += kps[:, 2].tolist()
    assert 2 in flags


def test_keypoints_are_projections_of_the_pose(tiny_split: Path) -> None:
    """Labels equal K (R X + t) of the manifest's 3D keypoints (pixel-corner origin convention)."""
    coco = _coco(tiny_split)
    manifest = build_manifest()
    names = {c["id"]: c["name"] for c in coco["categories"]}
    for ann in coco["annotations"]:
        pts = np.array(manifest.object(names[ann["category_id"]]).keypoints_3d)  # mm
        cam = pts @ np.array(ann["cam_R_m2c"]).T + np.array(ann["cam_t_m2c"])
        uvw = cam @ np.array(ann["cam_K"]).T
        proj = uvw[:, :2] / uvw[:, 2:]
        np.testing.assert_allclose(proj, np.array(ann["keypoints"]).reshape(-1, 3)[:, :2], atol=0.01)


def test_same_seed_same_data(tiny_split: Path, tmp_path: Path) -> None:
    again = tmp_path / "again"
    generate(again, TINY_IMAGES, TINY_SEED, "smoke", progress=False)
    assert _coco(again)["annotations"] == _coco(tiny_split)["annotations"]
    for im in _coco(again)["images"]:
        assert (again / im["file_name"]).read_bytes() == (tiny_split / im["file_name"]).read_bytes()
