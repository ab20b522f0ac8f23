"""A manifest that breaks the contract stops every command, naming the field.

The commands run their main in this process (tests/cli_calls.py); uvicorn started directly on the
app, a process, is tests/live/test_installed_commands.py's. Each case serves a copy of the bundled
model with one manifest edit.
"""

from __future__ import annotations

import json
from collections.abc import Callable
from pathlib import Path

import pytest

from service.detector.session import file_sha256
from tests.api.test_manifest_change import copy_model
from tests.cli_calls import run
from tests.samples import Sample, model_dir


def duplicate_name(manifest: dict) -> str:
    manifest["keypoints"][3]["name"] = manifest["keypoints"][0]["name"]
    return "keypoints[3].name: 'duck_kp0' is also the name of keypoints[0]"


def top_k_too_large(manifest: dict) -> str:
    manifest["heatmap"]["top_k"] = 64 * 64 + 1
    return "heatmap.top_k: is 4097 but a 64x64 heatmap"


def temperature_without_softmax(manifest: dict) -> str:
    manifest["heatmap"]["temperature"] = 0.5
    return "heatmap.temperature: is 0.5 but normalization 'anchor' does not use a temperature"


def command_args(command: str, samples_dir: Path, samples: list[Sample]) -> list[str]:
    sample = samples[0]
    instance = f"{sample.object}:{','.join(f'{v:g}' for v in sample.bbox)}"
    return {
        "serve": ["serve"],
        "check-model": ["check-model"],
        "calibrate": ["calibrate", str(samples_dir)],
        "predict": ["predict", str(sample.image_path), "--instance", instance],
    }[command]


def edited_model(tmp_path: Path, edit: Callable[[dict], str]) -> tuple[Path, str]:
    """A copy of the bundled model with one manifest edit, and the line its refusal must contain."""
    model = copy_model(model_dir(), tmp_path / "model")
    manifest = json.loads((model / "manifest.json").read_text())
    problem = edit(manifest)
    (model / "manifest.json").write_text(json.dumps(manifest, indent=2))
    return model, f"{model / 'manifest.json'}: {problem}"


def refused(tmp_path: Path, edit: Callable[[dict], str], args: list[str]) -> tuple[str, str]:
    """Run a command on an edited copy; it must fail without a traceback. Returns (output, expected line)."""
    model, expected = edited_model(tmp_path, edit)
    result = run(args, tmp_path / "data", model_dir=model)
    output = result.stdout + result.stderr
    assert result.returncode != 0, output
    assert "Traceback" not in output, output
    return output, expected


@pytest.mark.parametrize("command", ["serve", "check-model", "calibrate", "predict"])
def test_duplicate_keypoint_names_stop_every_command(
    tmp_path: Path, samples_dir: Path, samples: list[Sample], command: str
) -> None:
    output, expected = refused(tmp_path, duplicate_name, command_args(command, samples_dir, samples))
    assert f"error: the model cannot be served: {expected}" in output, output


@pytest.mark.parametrize("edit", [top_k_too_large, temperature_without_softmax])
def test_check_model_names_the_field(tmp_path: Path, edit: Callable[[dict], str]) -> None:
    output, expected = refused(tmp_path, edit, ["check-model"])
    assert expected in output, output


def test_check_model_summarizes_the_bundled_model(model_path: Path, tmp_path: Path, manifest: dict) -> None:
    result = run(["check-model", str(model_path)], tmp_path)
    assert result.returncode == 0, result.stderr
    lines = result.stdout.splitlines()
    assert lines[0] == f"{model_path}: ok, model.onnx sha256 {file_sha256(model_path / 'model.onnx')}"
    assert lines[1] == f"name      {manifest['name']}"
    assert any(line.startswith("output    'heatmaps' (N, 48, 64, 64)") for line in lines), lines
    for obj in manifest["objects"]:
        assert any(line.startswith(f"  {obj['name']} (3D): ") for line in lines), lines
