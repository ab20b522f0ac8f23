"""An operator edits the manifest's heatmap settings: old versions are refused, never silently used.

The model hash covers the ONNX bytes only, so versions scored under the old top-K stay
listed for the same model; using their thresholds with the new statistics would void
the guarantee. Real uvicorn processes share one SQLite store across the edit.
"""

from __future__ import annotations

import json
import shutil
from pathlib import Path

from tests.service.live import ADMIN_TOKEN, LiveServer, Sample, assert_problem, batch_zip, samples_by_image
from tests.service.predict_client import instances_of, predict_json, predict_ok


def copy_model(source: Path, target: Path, top_k_change: int = 0) -> Path:
    target.mkdir(parents=True)
    for name in ("model.onnx", "manifest.json", "default_calibration.npz"):
        shutil.copyfile(source / name, target / name)
    manifest = json.loads((source / "manifest.json").read_text())
    manifest["heatmap"]["top_k"] += top_k_change
    (target / "manifest.json").write_text(json.dumps(manifest, indent=2))
    return target


def activation_count(server: LiveServer) -> int:
    response = server.client.get("/v1/admin/activations", headers=server.admin)
    assert response.status_code == 200, response.text
    return len(response.json()["activations"])


def test_versions_scored_under_other_heatmap_settings_are_refused(
    model_path: Path, samples_dir: Path, coco: dict, samples: list[Sample], tmp_path: Path
) -> None:
    image_path, group = next(iter(samples_by_image(samples).items()))
    request = {"instances": instances_of(group)}
    data = tmp_path / "data"
    original = copy_model(model_path, tmp_path / "original")
    with LiveServer(data, admin_token=ADMIN_TOKEN, model_dir=original) as server:
        predict_ok(server.client, image_path.read_bytes(), request)  # the bundled version 1
        server.calibrate(batch_zip(samples_dir, coco, images=4))  # version 2, not active

    edited = copy_model(model_path, tmp_path / "edited", top_k_change=7)
    with LiveServer(data, admin_token=ADMIN_TOKEN, model_dir=edited) as server:
        assert server.versions() == [1, 2]  # same model hash, no second bootstrap
        assert_problem(server.client.get("/readyz"), 503, "calibration version 1 cannot be used", "top_k")
        for version in (None, 2):
            body = {**request, "calibration_version": version} if version else request
            assert_problem(
                predict_json(server.client, image_path.read_bytes(), body),
                409, f"calibration version {version or 1} cannot be used", "calibrate a new version",
            )  # fmt: skip
        before = activation_count(server)
        response = server.client.post("/v1/admin/calibrations/2/activate", headers=server.admin)
        assert_problem(response, 409, "calibration version 2 cannot be used")
        assert activation_count(server) == before  # nothing stored
        response = server.upload(batch_zip(samples_dir, coco, images=2), append_to=2)
        assert_problem(response, 409, "cannot append", "top_k")
        assert server.versions() == [1, 2]

        server.calibrate(batch_zip(samples_dir, coco, images=4), activate=True)  # version 3, new settings
        assert server.client.get("/readyz").json()["active_calibration"] == 3
        predict_ok(server.client, image_path.read_bytes(), request)


def test_a_bundle_scored_under_other_settings_is_not_bootstrapped(model_path: Path, tmp_path: Path) -> None:
    edited = copy_model(model_path, tmp_path / "edited", top_k_change=-1)
    with LiveServer(tmp_path / "data", admin_token=ADMIN_TOKEN, model_dir=edited) as server:
        assert server.versions() == []
        assert_problem(server.client.get("/readyz"), 503, "no calibration is active")
        assert "is not loaded" in server.log() and "top_k" in server.log()
