"""COCO-keypoints calibration batches: a real folder with real images, then one defect at a time."""

from __future__ import annotations

import copy
import hashlib
import json
import struct
from collections.abc import Callable
from pathlib import Path
from typing import Any

import cv2
import numpy as np
import pytest

from service.calibration import coco
from service.calibration.coco import CocoBatch, load_coco_batch
from service.detector.manifest import Manifest
from service.errors import InvalidInput

MANIFEST = Manifest.model_validate(
    {
        "name": "toy",
        "input": {"name": "image", "height": 64, "width": 64},
        "output": {"name": "heatmaps", "height": 16, "width": 16},
        "keypoints": [
            {"index": 0, "name": "bill", "object": "duck"},
            {"index": 1, "name": "tail", "object": "duck"},
            {"index": 2, "name": "foot", "object": "duck"},
            {"index": 3, "name": "handle", "object": "mug"},
            {"index": 4, "name": "rim", "object": "mug"},
        ],
        "objects": [{"name": "duck", "keypoints": [0, 1, 2]}, {"name": "mug", "keypoints": [3, 4]}],
    }
)


def write_image(path: Path, width: int, height: int) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    ok, buf = cv2.imencode(path.suffix, np.full((height, width, 3), 128, np.uint8))
    assert ok
    path.write_bytes(buf.tobytes())


def valid_document() -> dict[str, Any]:
    return {
        "info": {"description": "extra sections are ignored"},
        "images": [
            {"id": 1, "file_name": "a.jpg", "width": 64, "height": 48},
            {"id": 2, "file_name": "images/b.png", "width": 32, "height": 32, "license": 3},
        ],
        "categories": [
            {"id": 1, "name": "duck", "keypoints": ["bill", "tail", "foot"], "supercategory": "toy"},
            {"id": 2, "name": "mug", "keypoints": ["handle", "rim"]},
            {"id": 9, "name": "person", "keypoints": ["nose"]},  # unused: harmless
        ],
        "annotations": [
            {
                "id": 10,
                "image_id": 1,
                "category_id": 1,
                "bbox": [4, 5, 40, 30],
                "keypoints": [10, 12, 2, 70.5, -3, 1, 0, 0, 0],  # tail outside the image, foot unlabeled
                "num_keypoints": 2,
                "area": 1200,
                "iscrowd": 0,
            },
            {
                "id": 11,
                "image_id": 1,
                "category_id": 2,
                "bbox": [0, 0, 64, 48],
                "keypoints": [1, 2, 2, 3, 4, 2],
            },
            {
                "id": 12,
                "image_id": 2,
                "category_id": 2,
                "bbox": [1.5, 2.5, 20, 20],
                "keypoints": [5, 6, 2.0, 0, 0, 0],
            },
        ],
    }


def write_batch(folder: Path, doc: Any) -> Path:
    folder.mkdir(parents=True, exist_ok=True)
    write_image(folder / "a.jpg", 64, 48)
    write_image(folder / "images" / "b.png", 32, 32)
    text = doc if isinstance(doc, str) else json.dumps(doc)
    (folder / "annotations.json").write_text(text)
    return folder


@pytest.fixture
def folder(tmp_path: Path) -> Path:
    return write_batch(tmp_path / "batch", valid_document())


Edit = Callable[[dict[str, Any]], None]


def refusal(tmp_path: Path, edit: Edit) -> InvalidInput:
    doc = copy.deepcopy(valid_document())
    edit(doc)
    folder = write_batch(tmp_path / "batch", doc)
    with pytest.raises(InvalidInput) as info:
        load_coco_batch(folder, MANIFEST)
    return info.value


def only_error(error: InvalidInput) -> str:
    assert len(error.errors) == 1, error.errors
    assert error.errors[0] in error.detail
    return error.errors[0]


class TestValidBatch:
    def test_instances(self, folder: Path) -> None:
        batch = load_coco_batch(folder, MANIFEST)
        assert isinstance(batch, CocoBatch) and batch.count == 3
        duck = batch.instances[0]
        assert (duck.image_id, duck.annotation_id, duck.object_name) == (1, 10, "duck")
        assert duck.bbox.dtype == np.float64 and duck.bbox.shape == (4,)
        np.testing.assert_array_equal(duck.bbox, [4, 5, 40, 30])
        assert duck.keypoints.dtype == np.float64 and duck.keypoints.shape == (3, 2)
        np.testing.assert_array_equal(duck.keypoints[:2], [[10, 12], [70.5, -3]])  # v=1 counts as labeled
        assert np.isnan(duck.keypoints[2]).all()
        np.testing.assert_array_equal(~np.isnan(duck.keypoints[:, 0]), [True, True, False])
        assert batch.instances[2].keypoints.shape == (2, 2)
        assert np.count_nonzero(~np.isnan(batch.instances[2].keypoints[:, 0])) == 1

    def test_arrays_are_read_only(self, folder: Path) -> None:
        instance = load_coco_batch(folder, MANIFEST).instances[0]
        with pytest.raises(ValueError):
            instance.keypoints[0, 0] = 1.0
        with pytest.raises(ValueError):
            instance.bbox[0] = 1.0

    def test_images(self, folder: Path) -> None:
        batch = load_coco_batch(folder, MANIFEST)
        assert set(batch.images) == {1, 2}
        image = batch.images[2]
        assert image.path == (folder / "images" / "b.png").resolve() and image.path.is_file()
        assert (image.width, image.height, image.file_name) == (32, 32, "images/b.png")

    def test_grouping(self, folder: Path) -> None:
        groups = load_coco_batch(folder, MANIFEST).instances_by_image()
        assert {k: [i.annotation_id for i in v] for k, v in groups.items()} == {1: [10, 11], 2: [12]}

    def test_sha256_of_annotations(self, folder: Path) -> None:
        expected = hashlib.sha256((folder / "annotations.json").read_bytes()).hexdigest()
        assert load_coco_batch(folder, MANIFEST).sha256 == expected

    def test_box_within_tolerance(self, tmp_path: Path) -> None:
        doc = valid_document()
        doc["annotations"][1]["bbox"] = [-0.9, -0.5, 64.8, 48.9]
        assert load_coco_batch(write_batch(tmp_path / "b", doc), MANIFEST).count == 3

    def test_large_jpeg_header_segments(self, folder: Path) -> None:
        """The header is found even when metadata before the frame header exceeds the first read."""
        data = (folder / "a.jpg").read_bytes()
        comment = b"\xff\xfe" + struct.pack(">H", 65535) + b"c" * 65533
        (folder / "a.jpg").write_bytes(data[:2] + comment * 2 + data[2:])
        assert load_coco_batch(folder, MANIFEST).count == 3


class TestDocument:
    @pytest.mark.parametrize(
        ("text", "message"),
        [
            ('{"images": [', "not valid JSON"),
            ("\xff\xfe garbage", "not valid JSON"),
            ("[" * 100_000 + "]" * 100_000, "not valid JSON"),
            ("[]", "must be a JSON object"),
            ('"text"', "must be a JSON object"),
        ],
        ids=["truncated", "binary", "deeply-nested", "list", "string"],
    )
    def test_not_a_coco_object(self, tmp_path: Path, text: str, message: str) -> None:
        folder = write_batch(tmp_path / "b", text)
        with pytest.raises(InvalidInput, match=message):
            load_coco_batch(folder, MANIFEST)

    def test_missing_and_mistyped_sections(self, tmp_path: Path) -> None:
        error = refusal(tmp_path, lambda d: (d.pop("images"), d.update(annotations={})))
        assert "images: is missing" in error.errors[0]
        assert "annotations: must be a list, got an object" in error.errors[1]

    def test_missing_annotations_file(self, folder: Path) -> None:
        (folder / "annotations.json").unlink()
        with pytest.raises(InvalidInput, match="annotations.json is missing"):
            load_coco_batch(folder, MANIFEST)

    def test_empty_batch(self, tmp_path: Path) -> None:
        error = refusal(tmp_path, lambda d: d.update(annotations=[]))
        assert "annotations: is empty" in only_error(error)

    def test_entries_of_the_wrong_type(self, tmp_path: Path) -> None:
        def edit(d: dict[str, Any]) -> None:
            d["images"].append("c.jpg")
            d["categories"].append(None)
            d["annotations"].append([1, 2])

        error = refusal(tmp_path, edit)
        assert error.errors == [
            "categories[3]: must be an object, got null",
            "images[2]: must be an object, got a string",
            "annotations[3]: must be an object, got a list",
        ]


class TestCategories:
    def test_unknown_object(self, tmp_path: Path) -> None:
        error = refusal(tmp_path, lambda d: d["categories"][0].update(name="duk"))
        message = only_error(error)
        assert message == "annotations[0]: category 'duk' is not an object of model 'toy' (known: duck, mug)"

    def test_unknown_category_id(self, tmp_path: Path) -> None:
        error = refusal(tmp_path, lambda d: d["annotations"][2].update(category_id=5))
        assert only_error(error) == "annotations[2]: category_id 5 is not among the categories (ids: 1, 2, 9)"

    def test_duplicate_category_id(self, tmp_path: Path) -> None:
        error = refusal(tmp_path, lambda d: d["categories"][2].update(id=1))
        assert only_error(error) == "categories[2]: duplicate category id 1"

    def test_keypoint_names_count(self, tmp_path: Path) -> None:
        error = refusal(tmp_path, lambda d: d["categories"][1]["keypoints"].append("base"))
        assert "category 'mug' lists 3 keypoint names but model object 'mug' has 2" in only_error(error)


class TestAnnotations:
    def test_keypoint_count(self, tmp_path: Path) -> None:
        error = refusal(tmp_path, lambda d: d["annotations"][0]["keypoints"].extend([1, 1, 2]))
        assert only_error(error) == (
            "annotations[0].keypoints: has 12 numbers but object 'duck' has 3 keypoints "
            "(expected 3 x 3 = 9 values x, y, v)"
        )

    @pytest.mark.parametrize(
        ("value", "message"),
        [
            (float("nan"), "is not a finite number (nan)"),
            (float("inf"), "is not a finite number (inf)"),
            ("NaN", "is not a finite number ('NaN')"),
            ("-Infinity", "is not a finite number ('-Infinity')"),
            ("12", "must be a number, got a string '12'"),
            (None, "must be a number, got null None"),
            (True, "must be a number, got a boolean True"),
            (10**400, "is not a finite number"),
        ],
    )
    def test_non_finite_keypoints(self, tmp_path: Path, value: Any, message: str) -> None:
        error = refusal(tmp_path, lambda d: d["annotations"][1]["keypoints"].__setitem__(3, value))
        assert only_error(error).startswith(f"annotations[1].keypoints[3]: {message}")

    def test_non_finite_literals_in_json_text(self, tmp_path: Path) -> None:
        text = json.dumps(valid_document()).replace("[4, 5, 40, 30]", "[4, NaN, 1e999, -Infinity]")
        folder = write_batch(tmp_path / "b", text)
        with pytest.raises(InvalidInput) as info:
            load_coco_batch(folder, MANIFEST)
        assert [e.split(":")[0] for e in info.value.errors] == [
            "annotations[0].bbox[1]",
            "annotations[0].bbox[2]",
            "annotations[0].bbox[3]",
        ]

    def test_unlabeled_keypoints_must_still_be_finite(self, tmp_path: Path) -> None:
        error = refusal(tmp_path, lambda d: d["annotations"][0]["keypoints"].__setitem__(6, "nan"))
        assert only_error(error).startswith("annotations[0].keypoints[6]: is not a finite number")

    @pytest.mark.parametrize("v", [3, -1, 1.5])
    def test_visibility(self, tmp_path: Path, v: float) -> None:
        error = refusal(tmp_path, lambda d: d["annotations"][0]["keypoints"].__setitem__(5, v))
        assert only_error(error) == (
            f"annotations[0].keypoints[5]: visibility of keypoint 1 ('tail') is {v:g}; "
            "use 0 (not labeled), 1 (occluded) or 2 (visible)"
        )

    @pytest.mark.parametrize(
        ("bbox", "message"),
        [
            ([1, 2, 3], "has 3 numbers, expected 4"),
            ("1,2,3,4", "must be a list of 4 numbers, got a string"),
        ],
    )
    def test_malformed_bbox(self, tmp_path: Path, bbox: Any, message: str) -> None:
        error = refusal(tmp_path, lambda d: d["annotations"][1].update(bbox=bbox))
        assert only_error(error).startswith("annotations[1].bbox: ") and message in error.errors[0]

    @pytest.mark.parametrize(
        ("bbox", "message"),
        [
            ([1, 2, 0, 5], "at least 1 pixel, got w=0, h=5"),
            ([1, 2, 5, -1], "at least 1 pixel, got w=5, h=-1"),
            ([1, 2, 1e-6, 1e-6], "at least 1 pixel, got w=1e-06, h=1e-06"),
            ([-2, 0, 10, 10], "box [-2, 0, 10, 10] (x, y, w, h) extends outside the 64x48 image"),
            ([0, -1.5, 10, 10], "extends outside the 64x48 image"),
            ([60, 0, 5.5, 10], "extends outside the 64x48 image"),
            ([0, 40, 10, 9.5], "extends outside the 64x48 image"),
        ],
    )
    def test_bbox_breaking_the_predict_rule_is_rejected(
        self, tmp_path: Path, bbox: Any, message: str
    ) -> None:
        doc = copy.deepcopy(valid_document())
        doc["annotations"][1]["bbox"] = bbox
        batch = load_coco_batch(write_batch(tmp_path / "batch", doc), MANIFEST)
        assert [i.annotation_id for i in batch.instances] == [10, 12]
        (rejection,) = batch.rejected
        assert (rejection.image_id, rejection.annotation_id) == (1, 11)
        assert rejection.reason.startswith("annotations[1].bbox: ") and message in rejection.reason
        assert batch.annotations == 3

    def test_unknown_image(self, tmp_path: Path) -> None:
        error = refusal(tmp_path, lambda d: d["annotations"][1].update(image_id=3))
        assert only_error(error) == "annotations[1]: image_id 3 is not an id in images"

    def test_duplicate_annotation_id(self, tmp_path: Path) -> None:
        error = refusal(tmp_path, lambda d: d["annotations"][2].update(id=10))
        assert only_error(error) == "annotations[2]: duplicate annotation id 10"

    @pytest.mark.parametrize("key", ["id", "image_id", "category_id"])
    def test_ids_must_be_integers(self, tmp_path: Path, key: str) -> None:
        error = refusal(tmp_path, lambda d: d["annotations"][0].update({key: "1"}))
        assert only_error(error) == f"annotations[0]: {key} must be an integer, got '1'"

    def test_all_problems_are_collected(self, tmp_path: Path) -> None:
        def edit(d: dict[str, Any]) -> None:
            d["annotations"][0]["keypoints"][0] = "inf"
            d["annotations"][1]["bbox"][2] = "wide"
            d["annotations"][2]["category_id"] = 9

        error = refusal(tmp_path, edit)
        assert len(error.errors) == 3
        assert "3 problem(s)" in error.detail
        assert "category 'person' is not an object of model 'toy'" in error.errors[2]

    def test_problems_are_capped(self, tmp_path: Path) -> None:
        def edit(d: dict[str, Any]) -> None:
            d["annotations"] = [
                {"id": i, "image_id": 1, "category_id": 1, "bbox": [0, 0, 1, 1], "keypoints": ["x"] * 9}
                for i in range(10)
            ]

        error = refusal(tmp_path, edit)
        assert len(error.errors) == coco.MAX_REPORTED_PROBLEMS + 1
        assert error.errors[-1] == "... and 40 more"
        assert "90 problem(s)" in error.detail


class TestImages:
    def test_duplicate_image_id(self, tmp_path: Path) -> None:
        error = refusal(tmp_path, lambda d: d["images"][1].update(id=1))
        assert error.errors == [
            "images[1]: duplicate image id 1",
            "annotations[2]: image_id 2 is not an id in images",
        ]

    @pytest.mark.parametrize(
        ("field", "value"), [("width", 0), ("height", -4), ("width", 64.0), ("id", None)]
    )
    def test_fields(self, tmp_path: Path, field: str, value: Any) -> None:
        error = refusal(tmp_path, lambda d: d["images"][0].update({field: value}))
        assert f"images[0]: {field} must be" in error.errors[0]

    def test_declared_size_must_match_the_file(self, tmp_path: Path) -> None:
        error = refusal(tmp_path, lambda d: d["images"][0].update(width=640, height=480))
        assert only_error(error) == (
            "images[0] ('a.jpg'): declares 640x480 but the file is 64x48 (width x height); fix width/height"
        )

    @pytest.mark.parametrize(
        ("file_name", "message"),
        [
            ("/etc/passwd", "absolute path"),
            ("C:/images/a.jpg", "absolute path"),
            ("../outside.jpg", "contains '..'"),
            ("images/../../outside.jpg", "contains '..'"),
            ("images\\b.png", "backslash"),
            ("nul\x00.jpg", "NUL"),
            ("missing.jpg", "the image file is missing from the batch"),
            ("images", "the image file is missing from the batch"),
            ("", "file_name must be a non-empty string"),
        ],
    )
    def test_unsafe_or_missing_file_names(self, tmp_path: Path, file_name: str, message: str) -> None:
        write_image(tmp_path / "outside.jpg", 64, 48)  # exists, but outside the batch
        error = refusal(tmp_path, lambda d: d["images"][0].update(file_name=file_name))
        assert message in error.errors[0] and error.errors[0].startswith("images[0]")

    def test_symlinked_file(self, folder: Path, tmp_path: Path) -> None:
        write_image(tmp_path / "elsewhere.jpg", 64, 48)
        (folder / "a.jpg").unlink()
        (folder / "a.jpg").symlink_to(tmp_path / "elsewhere.jpg")
        with pytest.raises(InvalidInput) as info:
            load_coco_batch(folder, MANIFEST)
        assert (
            only_error(info.value)
            == "images[0] ('a.jpg'): a.jpg is a symbolic link; images must be regular files"
        )

    def test_symlinked_folder(self, folder: Path, tmp_path: Path) -> None:
        (folder / "images").rename(tmp_path / "real_images")
        (folder / "images").symlink_to(tmp_path / "real_images")
        with pytest.raises(InvalidInput, match="images is a symbolic link"):
            load_coco_batch(folder, MANIFEST)

    def test_symlinked_annotations(self, folder: Path, tmp_path: Path) -> None:
        (folder / "annotations.json").rename(tmp_path / "real.json")
        (folder / "annotations.json").symlink_to(tmp_path / "real.json")
        with pytest.raises(InvalidInput, match="annotations.json is missing"):
            load_coco_batch(folder, MANIFEST)

    def test_not_an_image(self, folder: Path) -> None:
        (folder / "a.jpg").write_bytes(b"GIF89a" + b"\x00" * 100)
        with pytest.raises(InvalidInput) as info:
            load_coco_batch(folder, MANIFEST)
        assert only_error(info.value) == "images[0] ('a.jpg'): is not a JPEG or PNG image"

    def test_unreadable_header(self, folder: Path) -> None:
        (folder / "images" / "b.png").write_bytes(b"\x89PNG\r\n\x1a\n\x00")
        with pytest.raises(InvalidInput) as info:
            load_coco_batch(folder, MANIFEST)
        assert "images[1] ('images/b.png'): cannot be read as an image (the PNG image is truncated" in (
            only_error(info.value)
        )
