"""Every bad calibration upload is refused with a precise 4xx and leaves nothing stored.

"Nothing stored" means: the list of versions is unchanged, the active version is unchanged,
the data directory's uploads/ folder is empty, and no file appeared outside the data directory.
"""

from __future__ import annotations

import hashlib
import math
import zipfile
from collections.abc import Callable
from pathlib import Path

import numpy as np
import pytest

from tests.api.in_process import InProcess
from tests.samples import batch_files, batch_zip, build_zip
from tests.service_calls import assert_problem


def snapshot(api: InProcess) -> tuple[list[int], int, list[Path]]:
    active = api.client.get("/readyz").json()["active_calibration"]
    root = api.data_dir.parent
    outside = sorted(p for p in root.rglob("*") if not p.is_relative_to(api.data_dir))
    return api.versions(), active, outside


def assert_nothing_stored(api: InProcess, before: tuple) -> None:
    assert snapshot(api) == before
    assert api.upload_workspaces() == [], "an upload workspace was left behind"


@pytest.fixture
def unchanged(limited_api: InProcess):
    """Asserts after the test that the refusal stored nothing."""
    before = snapshot(limited_api)
    yield
    assert_nothing_stored(limited_api, before)


def first_annotation(doc: dict) -> dict:
    return doc["annotations"][0]


def image_of(doc: dict, annotation: dict) -> dict:
    return next(image for image in doc["images"] if image["id"] == annotation["image_id"])


def rename_category(doc: dict, files: dict) -> None:
    category_id = first_annotation(doc)["category_id"]
    for category in doc["categories"]:
        if category["id"] == category_id:
            category["name"] = "no-such-object"


def drop_one_keypoint(doc: dict, files: dict) -> None:
    first_annotation(doc)["keypoints"] = first_annotation(doc)["keypoints"][:-3]


def delete_image_file(doc: dict, files: dict) -> None:
    del files[image_of(doc, first_annotation(doc))["file_name"]]


def box_outside(doc: dict, files: dict) -> None:
    annotation = first_annotation(doc)
    annotation["bbox"][0] = image_of(doc, annotation)["width"] + 10


def nan_keypoint(doc: dict, files: dict) -> None:
    first_annotation(doc)["keypoints"][0] = math.nan  # json.dumps writes NaN


def infinite_bbox(doc: dict, files: dict) -> None:
    first_annotation(doc)["bbox"][2] = math.inf  # json.dumps writes Infinity


def gif_image(doc: dict, files: dict) -> None:
    files[image_of(doc, first_annotation(doc))["file_name"]] = b"GIF89a" + b"\x00" * 100


def wrong_declared_size(doc: dict, files: dict) -> None:
    image_of(doc, first_annotation(doc))["width"] += 1


def traversal(doc: dict, files: dict) -> None:
    files["../escaped.txt"] = b"outside"


def absolute_path(doc: dict, files: dict) -> None:
    files["/tmp/escaped-absolute.txt"] = b"outside"


def traversal_in_file_name(doc: dict, files: dict) -> None:
    image_of(doc, first_annotation(doc))["file_name"] = "../../escaped.jpg"


CASES: dict[str, tuple[Callable[[dict, dict], None], int, tuple[str, ...]]] = {
    "unknown object name": (rename_category, 422, ("'no-such-object'", "is not an object of model")),
    "keypoint count": (drop_one_keypoint, 422, ("annotations[0].keypoints", "keypoints")),
    "missing image file": (delete_image_file, 422, ("missing",)),
    "box outside the image": (box_outside, 422, ("annotations[0].bbox", "outside")),
    "NaN keypoint": (nan_keypoint, 422, ("annotations[0].keypoints[0]", "finite")),
    "infinite bbox": (infinite_bbox, 422, ("annotations[0].bbox[2]", "finite")),
    "GIF image": (gif_image, 422, ("not a jpeg or png",)),
    "declared size differs": (wrong_declared_size, 422, ("width",)),
    "path traversal in the zip": (traversal, 422, ("../escaped.txt", "traversal")),
    "absolute path in the zip": (absolute_path, 422, ("absolute",)),
    "path traversal in file_name": (traversal_in_file_name, 422, ("..",)),
}


@pytest.mark.parametrize("case", list(CASES))
@pytest.mark.usefixtures("unchanged")
def test_bad_batch_is_refused(limited_api: InProcess, samples_dir: Path, coco: dict, case: str) -> None:
    mutate, status, fragments = CASES[case]
    body = batch_zip(samples_dir, coco, images=2, mutate=mutate)
    assert_problem(limited_api.upload(body, activate=True), status, *fragments)


@pytest.mark.usefixtures("unchanged")
def test_invalid_json_annotations(limited_api: InProcess, samples_dir: Path, coco: dict) -> None:
    _, files = batch_files(samples_dir, coco, images=2)
    body = build_zip(b'{"images": [{"id": 1,', files)
    assert_problem(limited_api.upload(body), 422, "annotations.json", "not valid json")


@pytest.mark.usefixtures("unchanged")
def test_annotations_not_an_object(limited_api: InProcess, samples_dir: Path, coco: dict) -> None:
    _, files = batch_files(samples_dir, coco, images=2)
    assert_problem(limited_api.upload(build_zip(b"[1, 2]", files)), 422, "annotations.json")


@pytest.mark.usefixtures("unchanged")
def test_symlink_in_the_zip(limited_api: InProcess, samples_dir: Path, coco: dict) -> None:
    doc, files = batch_files(samples_dir, coco, images=2)
    body = build_zip(doc, files, links={"images/link.jpg": "/etc/passwd"})
    assert_problem(limited_api.upload(body), 422, "images/link.jpg", "symbolic link")


@pytest.mark.usefixtures("unchanged")
def test_not_a_zip(limited_api: InProcess) -> None:
    assert_problem(limited_api.upload(b"this is not a zip archive"), 422, "zip")


@pytest.mark.usefixtures("unchanged")
def test_body_over_the_upload_limit(
    limited_api: InProcess, samples_dir: Path, coco: dict, limits: dict
) -> None:
    doc, files = batch_files(samples_dir, coco, images=2)
    files["noise.bin"] = np.random.default_rng(0).bytes(limits["max_upload_bytes"])
    body = build_zip(doc, files, compression=zipfile.ZIP_STORED)
    assert len(body) > limits["max_upload_bytes"]
    assert_problem(limited_api.upload(body), 413, "CKS_MAX_UPLOAD_BYTES")


@pytest.mark.usefixtures("unchanged")
def test_streamed_body_over_the_upload_limit(limited_api: InProcess, limits: dict) -> None:
    """Chunked transfer (no Content-Length): the limit holds while streaming."""

    def chunks():
        for _ in range(limits["max_upload_bytes"] // 65536 + 2):
            yield bytes(65536)

    response = limited_api.client.post(
        "/v1/admin/calibrations",
        content=chunks(),
        headers={**limited_api.admin, "Content-Type": "application/zip"},
    )
    assert_problem(response, 413, "CKS_MAX_UPLOAD_BYTES")


@pytest.mark.parametrize("content_type", ["application/json", "text/plain", "application/zip"])
@pytest.mark.usefixtures("unchanged")
def test_no_zip_is_refused_whatever_its_type(limited_api: InProcess, content_type: str) -> None:
    assert_problem(limited_api.upload(b"a zip starts with PK", content_type=content_type), 422, "zip")


def multipart(*parts: tuple[str, bytes], boundary: str = "cut-here", close: bool = True) -> bytes:
    body = b"".join(
        f'--{boundary}\r\nContent-Disposition: form-data; name="{name}"; filename="b.zip"\r\n'.encode()
        + b"Content-Type: application/zip\r\n\r\n"
        + data
        + b"\r\n"
        for name, data in parts
    )
    return body + (f"--{boundary}--\r\n".encode() if close else b"")


@pytest.mark.parametrize(
    ("parts", "content_type", "fragment"),
    [
        ([("file", b"PK")], "multipart/form-data", "boundary"),
        (
            [("name", b"x"), ("file", b"PK")],
            "multipart/form-data; boundary=cut-here",
            "unexpected multipart part 'name'",
        ),
        ([("file", b"PK"), ("file", b"PK")], "multipart/form-data; boundary=cut-here", "more than once"),
        ([], "multipart/form-data; boundary=cut-here", "'file' (the zip file) is missing"),
    ],
)
@pytest.mark.usefixtures("unchanged")
def test_a_malformed_form_is_refused(
    limited_api: InProcess, parts: list, content_type: str, fragment: str
) -> None:
    assert_problem(limited_api.upload(multipart(*parts), content_type=content_type), 422, fragment)


@pytest.mark.usefixtures("unchanged")
def test_a_form_cut_short_or_over_the_limit_is_refused(
    limited_api: InProcess, samples_dir: Path, coco: dict, limits: dict
) -> None:
    form = "multipart/form-data; boundary=cut-here"
    body = multipart(("file", batch_zip(samples_dir, coco, images=2)), close=False)
    assert_problem(limited_api.upload(body, content_type=form), 422, "closing boundary")
    huge = multipart(("file", b"\0" * (limits["max_upload_bytes"] + 1)))
    assert_problem(limited_api.upload(huge, content_type=form), 413, "CKS_MAX_UPLOAD_BYTES")


def test_a_form_with_the_zip_is_taken_as_the_zip(
    limited_api: InProcess, samples_dir: Path, coco: dict
) -> None:
    zipped = batch_zip(samples_dir, coco, images=2)
    form = limited_api.client.post(
        "/v1/admin/calibrations",
        files={"file": ("batch.zip", zipped, "application/zip")},
        params={"name": "as-form"},
        headers=limited_api.admin,
    )
    assert form.status_code == 202, form.text
    job = limited_api.wait_job(form.json()["id"])
    assert job["state"] == "succeeded", job
    detail = limited_api.client.get(f"/v1/admin/calibrations/{job['version']}", headers=limited_api.admin)
    batches = detail.json()["source_batches"]
    assert batches[-1]["name"] == "as-form" and batches[-1]["sha256"] == hashlib.sha256(zipped).hexdigest()
    assert limited_api.upload_workspaces() == []


def many_annotations(samples_dir: Path, coco: dict, count: int, keypoints: bool = True) -> bytes:
    """The first two images with ``count`` copies of their first annotation (deflated: tiny)."""
    doc, files = batch_files(samples_dir, coco, images=2)
    first = first_annotation(doc) if keypoints else {"image_id": doc["images"][0]["id"], "category_id": 1}
    doc["annotations"] = [{**first, "id": number + 1} for number in range(count)]
    return build_zip(doc, files)


def test_an_annotations_file_over_its_limit_is_refused_before_it_is_unzipped(
    api: InProcess, samples_dir: Path, coco: dict
) -> None:
    """30,000 annotations of 8 keypoints: 20 MB of JSON in a zip of about 0.2 MB, above the 16 MiB
    that annotations.json may take."""
    before = snapshot(api)
    body = many_annotations(samples_dir, coco, 30_000)
    assert len(body) < 1_000_000
    problem = assert_problem(api.upload(body), 413, "annotations.json")
    assert "above the limit of 16777216 bytes" in problem["detail"], problem
    assert_nothing_stored(api, before)


def test_more_annotations_than_the_limit_are_refused_before_any_is_read(
    api: InProcess, samples_dir: Path, coco: dict
) -> None:
    """20,001 small annotations fit in the bytes limit; the limit of 20,000 annotations refuses them."""
    before = snapshot(api)
    body = many_annotations(samples_dir, coco, 20_001, keypoints=False)
    problem = assert_problem(api.upload(body), 413, "20001 annotations")
    assert "above the limit of 20000" in problem["detail"], problem
    assert_nothing_stored(api, before)
