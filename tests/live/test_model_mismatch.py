"""Bring your own model: a manifest that does not fit the ONNX graph is refused at start-up.

Each case copies model.onnx into a temporary directory next to a modified manifest (the
bundled model directory is never written to). ``serve`` runs its main in this process; uvicorn
started directly on the app, a process, is tests/live/test_installed_commands.py's.
"""

from __future__ import annotations

import copy
import json
import shutil
from collections.abc import Callable
from pathlib import Path

import pytest

from service.detector.session import Detector, ModelMismatch
from tests.cli_calls import run
from tests.live.server import free_port


def wrong_input_name(manifest: dict) -> list[str]:
    manifest["input"]["name"] = "not_the_input"
    return ["not_the_input", "input"]


def wrong_output_name(manifest: dict) -> list[str]:
    manifest["output"]["name"] = "not_the_output"
    return ["not_the_output", "output"]


def wrong_heatmap_size(manifest: dict) -> list[str]:
    height = manifest["output"]["height"]
    manifest["output"]["height"] = height // 2
    return ["height", str(height), str(height // 2)]


def wrong_keypoint_count(manifest: dict) -> list[str]:
    """Drop the last object and its keypoints (renumbered): the graph still has the original count."""
    total = len(manifest["keypoints"])
    dropped = manifest["objects"].pop()
    kept = sorted(
        (k for k in manifest["keypoints"] if k["object"] != dropped["name"]), key=lambda k: k["index"]
    )
    renumber = {k["index"]: i for i, k in enumerate(kept)}
    manifest["keypoints"] = [{**k, "index": renumber[k["index"]]} for k in kept]
    for obj in manifest["objects"]:
        obj["keypoints"] = [renumber[i] for i in obj["keypoints"]]
    return ["keypoints", str(total), str(len(kept))]


CASES: dict[str, Callable[[dict], list[str]]] = {
    "input name": wrong_input_name,
    "output name": wrong_output_name,
    "heatmap size": wrong_heatmap_size,
    "keypoint count": wrong_keypoint_count,
}


def mismatched_model(source: Path, target: Path, case: str) -> list[str]:
    """A copy of the model with one manifest mismatch; returns what the message must name."""
    target.mkdir(parents=True)
    shutil.copyfile(source / "model.onnx", target / "model.onnx")
    manifest = copy.deepcopy(json.loads((source / "manifest.json").read_text()))
    fragments = CASES[case](manifest)
    (target / "manifest.json").write_text(json.dumps(manifest, indent=2))
    return fragments


@pytest.mark.parametrize("case", list(CASES))
def test_detector_refuses_the_mismatch(model_path: Path, tmp_path: Path, case: str) -> None:
    fragments = mismatched_model(model_path, tmp_path / "model", case)
    with pytest.raises(ModelMismatch) as raised:
        Detector(tmp_path / "model")
    for fragment in fragments:
        assert fragment in str(raised.value), f"{fragment!r} not in: {raised.value}"


def test_the_unmodified_copy_is_accepted(model_path: Path, tmp_path: Path) -> None:
    (tmp_path / "model").mkdir()
    for name in ("model.onnx", "manifest.json"):
        shutil.copyfile(model_path / name, tmp_path / "model" / name)
    assert (
        Detector(tmp_path / "model").manifest.name
        == json.loads((model_path / "manifest.json").read_text())["name"]
    )


@pytest.mark.parametrize("case", list(CASES))
def test_serve_exits_non_zero_naming_the_mismatch(model_path: Path, tmp_path: Path, case: str) -> None:
    fragments = mismatched_model(model_path, tmp_path / "model", case)
    result = run(["serve"], tmp_path / "data", model_dir=tmp_path / "model", port=free_port())
    output = result.stdout + result.stderr
    assert result.returncode != 0, output
    assert "cannot be served" in output
    for fragment in fragments:
        assert fragment in output, f"{fragment!r} not in: {output}"
