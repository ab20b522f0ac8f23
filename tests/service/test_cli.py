"""The keypoint-service command line: predict (JSON and PNG) and offline calibrate."""

from __future__ import annotations

import json
import subprocess
from pathlib import Path

import cv2
import numpy as np

from calibration_store import open_store
from service.detector.runtime import file_sha256
from service.settings import PACKAGE_ROOT
from tests.service.live import Sample, cli, count_instances, samples_by_image, service_env


def run(args: list[str], data_dir: Path) -> subprocess.CompletedProcess:
    result = subprocess.run(
        [*cli(), *args],
        env=service_env(data_dir),
        cwd=PACKAGE_ROOT,
        capture_output=True,
        text=True,
        timeout=180,
    )
    assert result.returncode == 0, (
        f"exit {result.returncode}\nstdout:\n{result.stdout}\nstderr:\n{result.stderr}"
    )
    return result


def test_predict_prints_json_and_writes_a_png(tmp_path: Path, samples: list[Sample]) -> None:
    path, group = next(iter(samples_by_image(samples).items()))
    instances = [f"{s.object}:{','.join(f'{v:g}' for v in s.bbox)}" for s in group]
    args = ["predict", str(path), "--png", str(tmp_path / "out.png"), "--nonconformity", "var"]
    for instance in instances:
        args += ["--instance", instance]
    body = json.loads(run(args, tmp_path / "data").stdout)

    image = cv2.imread(str(path), cv2.IMREAD_UNCHANGED)
    assert body["image"] == {"width": image.shape[1], "height": image.shape[0]}
    assert body["calibration"]["version"] == 1 and body["calibration"]["nonconformity"] == "var"
    assert [i["object"] for i in body["instances"]] == [s.object for s in group]
    for instance in body["instances"]:
        for keypoint in instance["keypoints"]:
            assert keypoint["set"]["type"] in ("ball", "unbounded")

    drawn = cv2.imread(str(tmp_path / "out.png"), cv2.IMREAD_COLOR)
    assert drawn is not None and drawn.shape[:2] == image.shape[:2]
    assert (tmp_path / "out.png").read_bytes().startswith(b"\x89PNG")
    assert np.any(drawn != cv2.imread(str(path), cv2.IMREAD_COLOR))


def test_calibrate_creates_and_activates_a_version(
    tmp_path: Path, samples_dir: Path, coco: dict, model_path: Path
) -> None:
    data = tmp_path / "data"
    data.mkdir()
    result = run(["calibrate", str(samples_dir), "--activate", "--note", "from the CLI"], data)
    summary = json.loads(result.stdout)
    assert summary == {"version": 1, "instances": count_instances(coco), "activated": True}

    model_hash = file_sha256(model_path / "model.onnx")
    with open_store(f"sqlite:///{data / 'calibrations.db'}") as store:
        (info,) = store.list_versions(model_hash)
        assert (info.number, info.note, info.n_instances) == (1, "from the CLI", count_instances(coco))
        assert store.active_version(model_hash).version == 1

    # appending through the CLI makes version 2 with both batches
    second = json.loads(
        run(["calibrate", str(samples_dir), "--append-to", "1", "--name", "again"], data).stdout
    )
    assert second == {"version": 2, "instances": 2 * count_instances(coco), "activated": False}
