"""An operator edits score-relevant manifest settings: old versions are refused, never silently used.

The model hash covers the ONNX bytes only, so versions scored under the old top-K (or
crop padding, input transform, channels) stay listed for the same model; using their
thresholds with the new statistics would void the guarantee. Services started in turn
on one data directory share its SQLite store across the edit.
"""

from __future__ import annotations

import json
import shutil
from collections.abc import Callable
from pathlib import Path

import pytest

from tests.api.in_process import InProcess
from tests.predict_client import instances_of, predict_json, predict_ok
from tests.samples import Sample, batch_zip, samples_by_image
from tests.service_calls import ADMIN_TOKEN, assert_problem


def more_top_k(manifest: dict) -> str:
    manifest["heatmap"]["top_k"] += 7
    return "heatmap top_k"


def fewer_top_k(manifest: dict) -> str:
    manifest["heatmap"]["top_k"] -= 1
    return "heatmap top_k"


def wider_crop(manifest: dict) -> str:
    manifest["crop"]["padding"] += 0.05
    return "fingerprint"


def renamed_keypoint(manifest: dict) -> None:
    manifest["keypoints"][0]["name"] += "_renamed"  # names do not change a score


def copy_model(source: Path, target: Path, edit: Callable[[dict], str | None] | None = None) -> Path:
    target.mkdir(parents=True)
    for name in ("model.onnx", "manifest.json", "default_calibration.npz"):
        shutil.copyfile(source / name, target / name)
    manifest = json.loads((source / "manifest.json").read_text())
    if edit is not None:
        edit(manifest)
    (target / "manifest.json").write_text(json.dumps(manifest, indent=2))
    return target


def activation_count(api: InProcess) -> int:
    response = api.client.get("/v1/admin/activations", headers=api.admin)
    assert response.status_code == 200, response.text
    return len(response.json()["activations"])


@pytest.mark.parametrize("edit", [more_top_k, wider_crop])
def test_versions_scored_under_other_manifest_settings_are_refused(
    model_path: Path, samples_dir: Path, coco: dict, samples: list[Sample], tmp_path: Path, edit: Callable
) -> None:
    image_path, group = next(iter(samples_by_image(samples).items()))
    request = {"instances": instances_of(group)}
    data = tmp_path / "data"
    original = copy_model(model_path, tmp_path / "original")
    with InProcess(data, admin_token=ADMIN_TOKEN, model_dir=original) as api:
        predict_ok(api.client, image_path.read_bytes(), request)  # the bundled version 1
        api.calibrate(batch_zip(samples_dir, coco, images=4))  # version 2, not active

    changed = edit(json.loads((model_path / "manifest.json").read_text()))
    edited = copy_model(model_path, tmp_path / "edited", edit)
    with InProcess(data, admin_token=ADMIN_TOKEN, model_dir=edited) as api:
        assert api.versions() == [1, 2]  # same model hash, no second bootstrap
        assert_problem(api.client.get("/readyz"), 503, "calibration version 1 cannot be used", changed)
        image = image_path.read_bytes()
        assert_problem(predict_json(api.client, image, request), 503, "the active calibration version 1")
        assert_problem(
            predict_json(api.client, image, {**request, "calibration_version": 2}),
            409,
            "calibration version 2 cannot be used",
            changed,
            "calibrate a new version",
        )
        detail = api.client.get("/v1/admin/calibrations/2", headers=api.admin).json()
        assert detail["usable"] is False and changed in detail["unusable_reason"]
        before = activation_count(api)
        response = api.client.post("/v1/admin/calibrations/2/activate", headers=api.admin)
        assert_problem(response, 409, "calibration version 2 cannot be used")
        assert activation_count(api) == before  # nothing stored
        response = api.upload(batch_zip(samples_dir, coco, images=2), append_to=2)
        assert_problem(response, 409, "cannot append", changed)
        assert api.versions() == [1, 2]

        # version 3, new settings: a small batch, so the guardrails want a reason
        body = batch_zip(samples_dir, coco, images=4)
        api.calibrate(body, activate=True, force=True, reason="re-scored")
        assert api.client.get("/readyz").json()["active_calibration"] == 3
        predict_ok(api.client, image, request)
        assert api.client.get("/v1/admin/calibrations/3", headers=api.admin).json()["usable"] is True


def test_a_bundle_scored_under_other_settings_is_not_bootstrapped(model_path: Path, tmp_path: Path) -> None:
    edited = copy_model(model_path, tmp_path / "edited", fewer_top_k)
    with InProcess(tmp_path / "data", admin_token=ADMIN_TOKEN, model_dir=edited) as api:
        assert api.versions() == []
        assert_problem(api.client.get("/readyz"), 503, "no calibration is active")
        assert "is not loaded" in api.log() and "top_k" in api.log()


def test_edits_that_do_not_change_scores_keep_the_versions(model_path: Path, tmp_path: Path) -> None:
    edited = copy_model(model_path, tmp_path / "edited", renamed_keypoint)
    with InProcess(tmp_path / "data", admin_token=ADMIN_TOKEN, model_dir=edited) as api:
        assert api.versions() == [1]
        assert api.client.get("/readyz").status_code == 200
