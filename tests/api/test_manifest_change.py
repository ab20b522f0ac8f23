"""An operator edits score-relevant manifest settings: old versions are refused, never silently used.

The model hash covers the ONNX bytes only, so versions scored under the old top-K (or
crop padding, input transform, channels) stay listed for the same model; using their
thresholds with the new statistics would void the guarantee. Real uvicorn processes
share one SQLite store across the edit.
"""

from __future__ import annotations

import json
import shutil
from collections.abc import Callable
from pathlib import Path

import pytest

from tests.live.server import LiveServer
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


def activation_count(server: LiveServer) -> int:
    response = server.client.get("/v1/admin/activations", headers=server.admin)
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
    with LiveServer(data, admin_token=ADMIN_TOKEN, model_dir=original) as server:
        predict_ok(server.client, image_path.read_bytes(), request)  # the bundled version 1
        server.calibrate(batch_zip(samples_dir, coco, images=4))  # version 2, not active

    changed = edit(json.loads((model_path / "manifest.json").read_text()))
    edited = copy_model(model_path, tmp_path / "edited", edit)
    with LiveServer(data, admin_token=ADMIN_TOKEN, model_dir=edited) as server:
        assert server.versions() == [1, 2]  # same model hash, no second bootstrap
        assert_problem(server.client.get("/readyz"), 503, "calibration version 1 cannot be used", changed)
        image = image_path.read_bytes()
        assert_problem(predict_json(server.client, image, request), 503, "the active calibration version 1")
        assert_problem(
            predict_json(server.client, image, {**request, "calibration_version": 2}),
            409, "calibration version 2 cannot be used", changed, "calibrate a new version",
        )  # fmt: skip
        detail = server.client.get("/v1/admin/calibrations/2", headers=server.admin).json()
        assert detail["usable"] is False and changed in detail["unusable_reason"]
        before = activation_count(server)
        response = server.client.post("/v1/admin/calibrations/2/activate", headers=server.admin)
        assert_problem(response, 409, "calibration version 2 cannot be used")
        assert activation_count(server) == before  # nothing stored
        response = server.upload(batch_zip(samples_dir, coco, images=2), append_to=2)
        assert_problem(response, 409, "cannot append", changed)
        assert server.versions() == [1, 2]

        # version 3, new settings: a small batch, so the guardrails want a reason
        body = batch_zip(samples_dir, coco, images=4)
        server.calibrate(body, activate=True, force=True, reason="re-scored")
        assert server.client.get("/readyz").json()["active_calibration"] == 3
        predict_ok(server.client, image, request)
        assert server.client.get("/v1/admin/calibrations/3", headers=server.admin).json()["usable"] is True


def test_a_bundle_scored_under_other_settings_is_not_bootstrapped(model_path: Path, tmp_path: Path) -> None:
    edited = copy_model(model_path, tmp_path / "edited", fewer_top_k)
    with LiveServer(tmp_path / "data", admin_token=ADMIN_TOKEN, model_dir=edited) as server:
        assert server.versions() == []
        assert_problem(server.client.get("/readyz"), 503, "no calibration is active")
        assert "is not loaded" in server.log() and "top_k" in server.log()


def test_edits_that_do_not_change_scores_keep_the_versions(model_path: Path, tmp_path: Path) -> None:
    edited = copy_model(model_path, tmp_path / "edited", renamed_keypoint)
    with LiveServer(tmp_path / "data", admin_token=ADMIN_TOKEN, model_dir=edited) as server:
        assert server.versions() == [1]
        assert server.client.get("/readyz").status_code == 200
