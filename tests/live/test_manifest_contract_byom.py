"""The worked example of docs/bring-your-own-model.md, end to end, exactly as the page tells it.

``docs/examples/export_simplebaseline.py`` exports a SimpleBaseline network to ONNX with a
manifest of its own (256x192 BGR input, 64x48 heatmaps, softmax with a temperature);
``keypoint-service check-model`` accepts it, ``keypoint-service calibrate`` scores the
bundled samples into a fresh SQLite store, and the service predicts with that calibration: every
keypoint's guarantee counts the calibration instances that label it. The script runs as
``__main__`` and the commands' ``main`` in this process, the service too (tests/api/in_process.py).
"""

from __future__ import annotations

import contextlib
import io
import json
import math
import re
import runpy
import sys
from pathlib import Path
from unittest import mock

from service.detector.session import file_sha256
from service.infra.settings import PACKAGE_ROOT
from tests.api.in_process import InProcess
from tests.cli_calls import run
from tests.predict_client import instances_of, predict_ok
from tests.samples import Sample, count_instances, samples_by_image

EXAMPLE = PACKAGE_ROOT / "docs" / "examples" / "export_simplebaseline.py"
PAGE = PACKAGE_ROOT / "docs" / "bring-your-own-model.md"
EPSILON = 0.2  # as on the page: the samples hold 7 to 11 instances per object


def succeeded(args: list[str], data: Path, model: Path) -> str:
    """``keypoint-service ARGS`` with CKS_MODEL_DIR naming ``model``; its stdout."""
    result = run(args, data, model_dir=model)
    assert result.returncode == 0, f"{args}: exit {result.returncode}\n{result.stdout}\n{result.stderr}"
    return result.stdout


def exported(model: Path) -> str:
    """``python docs/examples/export_simplebaseline.py --model-dir MODEL``, as ``__main__``; its stdout."""
    printed = io.StringIO()
    argv = [str(EXAMPLE), "--model-dir", str(model)]
    with mock.patch.object(sys, "argv", argv), contextlib.redirect_stdout(printed):
        runpy.run_path(str(EXAMPLE), run_name="__main__")
    return printed.getvalue()


def documented_manifest() -> dict:
    """The JSON block that follows the page's example-manifest marker."""
    text = PAGE.read_text(encoding="utf-8")
    match = re.search(r"<!-- example-manifest[^>]*-->\s*```json\n(.*?)```", text, re.DOTALL)
    assert match, "docs/bring-your-own-model.md lost its example manifest block"
    return json.loads(match.group(1))


def expected_counts(samples: list[Sample], scope: str) -> dict[tuple[str, int], int]:
    """(object, keypoint position) -> the guarantee's n: instances labeling it, or complete ones."""
    counts: dict[tuple[str, int], int] = {}
    for sample in samples:
        labeled = [v > 0 for _, _, v in sample.keypoints]
        for j, is_labeled in enumerate(labeled):
            counted = is_labeled if scope == "keypoint" else all(labeled)
            counts[(sample.object, j)] = counts.get((sample.object, j), 0) + int(counted)
    return counts


def test_the_worked_example_is_exported_checked_calibrated_and_served(
    tmp_path: Path, samples_dir: Path, coco: dict, samples: list[Sample]
) -> None:
    model, data = tmp_path / "simplebaseline-demo", tmp_path / "data"

    printed = exported(model)
    difference = float(re.search(r"max \|diff\| on random crops: (\S+)", printed).group(1))
    assert difference < 1e-4, printed
    manifest = json.loads((model / "manifest.json").read_text(encoding="utf-8"))
    bundled = json.loads((samples_dir.parent / "manifest.json").read_text(encoding="utf-8"))
    assert {k: v for k, v in manifest.items() if k not in ("keypoints", "objects")} == documented_manifest()
    assert [o["keypoints"] for o in manifest["objects"]] == [o["keypoints"] for o in bundled["objects"]]

    model_hash = file_sha256(model / "model.onnx")
    summary = succeeded(["check-model"], data, model).splitlines()  # CKS_MODEL_DIR names the model
    assert summary[0] == f"{model}: ok, model.onnx sha256 {model_hash}"
    assert "output    'heatmaps' (N, 48, 64, 48), stride 4 x 4 input pixels" in summary
    assert "heatmap   softmax (temperature 0.5), top_k 64" in summary

    command = ["calibrate", str(samples_dir), "--activate", "--force", "--reason", "worked example"]
    calibrated = json.loads(succeeded(command, data, model))
    assert (calibrated["version"], calibrated["instances"]) == (1, count_instances(coco))
    assert calibrated["activated"] is True  # forced: 52 instances are below the guardrails' floor

    image_path, group = next(iter(samples_by_image(samples).items()))
    with InProcess(data, model_dir=model) as server:
        served = server.client.get("/v1/model").json()
        assert (served["hash"], served["manifest"]) == (model_hash, manifest)
        for scope in ("keypoint", "object"):
            request = {"instances": instances_of(group), "epsilon": EPSILON, "coverage": scope}
            body = predict_ok(server.client, image_path.read_bytes(), request)
            assert body["model"] == {"name": "simplebaseline-demo", "hash": model_hash, "variant": "original"}
            assert body["calibration"]["version"] == 1
            counts = expected_counts(samples, scope)
            for sample, instance in zip(group, body["instances"], strict=True):
                assert instance["object"] == sample.object
                for j, keypoint in enumerate(instance["keypoints"]):
                    guarantee, n = keypoint["guarantee"], counts[(sample.object, j)]
                    assert (guarantee["scope"], guarantee["n"]) == (scope, n), keypoint
                    assert guarantee["t"] == math.floor((n + 1) * EPSILON) >= 1, keypoint
                    assert keypoint["set"]["type"] == "ellipse", keypoint  # cov, and bounded since t >= 1
