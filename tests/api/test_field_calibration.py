"""Recalibration from the field in process: the bundled samples predicted (retained) and labelled
through feedback become a version with the same stored scores, features and fingerprints as a zip
upload of the same images and labels, refused as a duplicate of it, and held to the upload's rules."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest

from calibration_store import ScoreTable
from tests.api.in_process import InProcess
from tests.predict_client import instances_of, predict_ok
from tests.samples import Sample, batch_zip, samples_by_image
from tests.service_calls import ADMIN_TOKEN, assert_problem

FROM_FEEDBACK = "/v1/admin/field-calibrations"


@pytest.fixture(scope="module")
def api(tmp_path_factory: pytest.TempPathFactory, samples: list[Sample]) -> Iterator[InProcess]:
    """Every sample image predicted (retained, stream cam-1) and labelled with its true points."""
    with InProcess(tmp_path_factory.mktemp("field") / "data", admin_token=ADMIN_TOKEN) as service:
        for path, group in samples_by_image(samples).items():
            options = {"instances": instances_of(group), "retain": True, "stream": "cam-1"}
            answer = predict_ok(service.client, Path(path).read_bytes(), options)
            labels = {"instances": [{"instance": i, "keypoints": s.keypoints} for i, s in enumerate(group)]}
            response = service.client.post(
                f"/v1/feedback/{answer['prediction_id']}", json=labels, headers=service.admin
            )
            assert response.status_code == 200, response.text
        yield service


def by_instance(table: ScoreTable) -> dict[str, tuple]:
    """instance hash -> (object, image hash, scores per function, features), the refs left out."""
    rows = {}
    for block in table.objects:
        for i, digest in enumerate(block.instance_hashes):
            scores = tuple(block.scores[kind][i] for kind in sorted(block.scores))
            features = tuple(block.features[name][i] for name in sorted(block.features))
            rows[digest] = (block.object_name, block.image_hashes[i], scores, features)
    return rows


def same(a: tuple, b: tuple) -> bool:
    return a[:2] == b[:2] and all(
        x.shape == y.shape and np.array_equal(x, y, equal_nan=True)
        for x, y in zip(a[2] + a[3], b[2] + b[3], strict=True)
    )


def test_feedback_makes_the_version_a_zip_upload_of_the_same_labels_makes(
    api: InProcess, samples_dir: Path, coco: dict
) -> None:
    response = api.client.post(FROM_FEEDBACK, json={"note": "field labels"}, headers=api.admin)
    assert response.status_code == 201, response.text
    field = response.json()
    assert field["version"] == 2 and not field["activated"]
    assert field["summary"]["instances"] == len(coco["annotations"]) and field["summary"]["rejected"] == 0
    # the zip of the same images and labels would repeat it: refused as its duplicate
    duplicate = api.upload(batch_zip(samples_dir, coco))
    assert_problem(duplicate, 409, "equal to calibration version 2")
    job = api.calibrate(batch_zip(samples_dir, coco), allow_duplicate=True, reason="the zip, for comparison")
    zipped = job["result"]["version"]
    store, model_hash = api.app.state.service.store, api.app.state.service.detector.model_hash
    from_field = by_instance(store.load_scores(model_hash, 2))
    from_zip = by_instance(store.load_scores(model_hash, zipped))
    assert from_field.keys() == from_zip.keys() and len(from_field) == len(coco["annotations"])
    assert all(same(from_field[k], from_zip[k]) for k in from_field)
    audit = api.client.get("/v1/admin/audit", headers=api.admin).json()["entries"]
    stored = [e for e in audit if e["action"] == "calibration" and e["version"] == 2]
    assert stored and stored[0]["who"] == "admin" and stored[0]["reason"] == "field labels"


def test_the_upload_rules_hold(api: InProcess) -> None:
    again = api.client.post(FROM_FEEDBACK, json={}, headers=api.admin)
    assert_problem(again, 409, "equal to calibration version")
    appended = api.client.post(FROM_FEEDBACK, json={"append_to": 2}, headers=api.admin)
    assert_problem(appended, 409, "already counted")
    dropped = api.client.post(FROM_FEEDBACK, json={"append_to": 2, "dedupe": True}, headers=api.admin)
    assert_problem(dropped, 422, "no labelled instance is left")
    assert_problem(
        api.client.post(FROM_FEEDBACK, json={"stream": "cam-2"}, headers=api.admin), 422, "no labelled"
    )
    assert_problem(
        api.client.post(FROM_FEEDBACK, json={"activate": True, "force": True}, headers=api.admin), 422
    )
    assert_problem(api.client.post(FROM_FEEDBACK, json={"append_to": 99}, headers=api.admin), 404)
    assert_problem(api.client.post(FROM_FEEDBACK, json={}), 401)


def test_activation_goes_through_the_guardrails(api: InProcess) -> None:
    body = {"activate": True, "allow_duplicate": True, "reason": "a copy to activate"}
    response = api.client.post(FROM_FEEDBACK, json=body, headers=api.admin)
    assert response.status_code == 201, response.text
    outcome = response.json()
    assert not outcome["activated"]  # 52 instances against the bundled calibration's 600: refused
    assert outcome["summary"]["activation_problems"]
    assert api.client.get("/readyz").json()["active_calibration"] == 1
