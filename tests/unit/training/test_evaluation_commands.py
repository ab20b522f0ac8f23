"""The detector evaluation and top-K selection commands, run on the committed sample."""

from __future__ import annotations

import shutil
from pathlib import Path

import numpy as np
import pytest

from service.detector.crop import apply_affines, invert_affines
from service.detector.manifest import load_manifest
from training import evaluate_detector, select_top_k

MODEL_DIR = Path(__file__).resolve().parents[3] / "models" / "lmo-synth-unet"
SAMPLES = MODEL_DIR / "samples"


def test_peak_point_is_the_argmax_pixel_centre_mapped_to_the_image() -> None:
    found = next(evaluate_detector.image_instances(SAMPLES, MODEL_DIR, max_images=1))
    manifest = load_manifest(MODEL_DIR)
    points = evaluate_detector.service_points(found.heatmaps, manifest, "peak")
    n, k, h, w = found.heatmaps.shape
    flat = found.heatmaps.reshape(n, k, -1).argmax(axis=2)
    np.testing.assert_array_equal(points, np.stack([flat % w + 0.5, flat // w + 0.5], axis=2))
    in_image = apply_affines(invert_affines(found.affines), points)
    assert in_image.shape == found.labels[:, :, :2].shape


def test_report_counts_every_labelled_keypoint_and_the_detector_is_accurate_on_visible_ones() -> None:
    result = evaluate_detector.collect_errors(SAMPLES, MODEL_DIR)
    summary = evaluate_detector.report(result)
    assert summary["visible"]["count"] + summary["occluded"]["count"] == np.count_nonzero(result["v"] > 0)
    assert summary["visible"]["pck"] > 0.6  # a detector that works, not a threshold of the quality bar
    assert summary["visible"]["median"] < summary["occluded"]["median"]


def copied_model(tmp_path: Path) -> Path:
    model = tmp_path / "model"
    shutil.copytree(MODEL_DIR, model, ignore=shutil.ignore_patterns("samples"))
    return model


def test_select_top_k_writes_the_k_with_the_smallest_cov_area(
    tmp_path: Path, capsys: pytest.CaptureFixture
) -> None:
    model = copied_model(tmp_path)
    options = ["--candidates", "4", "100", "--epsilon", "0.5", "--write"]
    select_top_k.main(["--data", str(SAMPLES), "--model", str(model), *options])
    out = capsys.readouterr().out
    rows = [line.split("|") for line in out.splitlines() if line.startswith(("| 4 ", "| 100 "))]
    cov_area = {int(r[1]): float(r[4]) for r in rows}
    assert set(cov_area) == {4, 100} and all(np.isfinite(list(cov_area.values())))
    assert cov_area[4] != cov_area[100]
    best = min(cov_area, key=cov_area.get)
    assert f"recommended top_k: {best}" in out and "recalibrate" in out
    written, committed = load_manifest(model), load_manifest(MODEL_DIR)
    assert written.heatmap.top_k == best
    assert written.model_copy(update={"heatmap": committed.heatmap}) == committed  # nothing else changed
    assert f"of {len(list((SAMPLES / 'images').iterdir()))} images" in out


def test_select_top_k_refuses_when_every_set_is_unbounded(tmp_path: Path) -> None:
    model = copied_model(tmp_path)
    before = (model / "manifest.json").read_bytes()
    with pytest.raises(SystemExit, match="unbounded"):  # 12 images: t = 0 for every keypoint at eps 0.1
        select_top_k.main(["--data", str(SAMPLES), "--model", str(model), "--candidates", "9", "--write"])
    assert (model / "manifest.json").read_bytes() == before
