"""Training targets, a one-step training smoke run, and ONNX export agreement with PyTorch."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from service.conformal import point_estimates
from service.detector.crop import apply_affines, invert_affines
from training.dataset import gaussian_targets, load_split, make_batch
from training.export import export
from training.manifest import build_manifest
from training.train import run


def argmax_points(heatmaps: np.ndarray) -> np.ndarray:
    """(N, K, H, W) -> (N, K, 2): the service's peak point (argmax pixel centre) of every map."""
    n, k, h, w = heatmaps.shape
    return point_estimates("peak", heatmaps.reshape(n * k, h, w)).reshape(n, k, 2)


def test_gaussian_target_peaks_at_the_label_pixel() -> None:
    points = np.array([[[10.2, 30.9], [0.5, 63.5]]])
    target = gaussian_targets(points, 64, 64)
    peaks = argmax_points(target)
    np.testing.assert_allclose(peaks, [[[10.5, 30.5], [0.5, 63.5]]])


def test_batch_targets_map_back_to_the_labels(tiny_split: Path) -> None:
    """Crop with the service's code, argmax the target, invert the affine: back at the label."""
    manifest = build_manifest()
    split = load_split(tiny_split, manifest, progress=False)
    rows = np.arange(len(split))
    inputs, targets, channels, points = make_batch(split, rows, manifest, rng=None)
    assert inputs.shape == (len(rows), 3, 128, 128) and inputs.dtype == np.float32
    assert targets.shape == (len(rows), 8, 64, 64)
    assert (channels // 8 == split.category[:, None]).all()
    from training.dataset import cut_crops

    _, affines = cut_crops(split, rows, split.boxes[rows], manifest)
    np.testing.assert_allclose(points, apply_affines(affines, split.keypoints[:, :, :2]), rtol=1e-5)
    back = apply_affines(invert_affines(affines), argmax_points(targets))
    inside = targets.max(axis=(2, 3)) > 0.5
    side = np.maximum(split.boxes[:, 2], split.boxes[:, 3])[:, None] * 1.25 / 64
    err = np.linalg.norm(back - split.keypoints[:, :, :2], axis=2)
    assert (err[inside] <= side.repeat(8, 1)[inside] * 0.71).all()


@pytest.fixture(scope="module")
def one_step_checkpoint(tiny_split: Path, tmp_path_factory: pytest.TempPathFactory) -> Path:
    manifest = build_manifest()
    split = load_split(tiny_split, manifest, progress=False)
    return run(split, tmp_path_factory.mktemp("run"), minutes=5, batch_size=4, max_steps=1, log_every=1)


def test_one_training_step_writes_a_resumable_checkpoint(one_step_checkpoint: Path, tiny_split: Path) -> None:
    import torch

    ckpt = torch.load(one_step_checkpoint, map_location="cpu", weights_only=False)
    assert ckpt["step"] == 1 and np.isfinite(ckpt["losses"][0][1])
    split = load_split(tiny_split, build_manifest(), progress=False)
    run(split, one_step_checkpoint.parent, minutes=5, batch_size=4, max_steps=2, resume=True)
    assert torch.load(one_step_checkpoint, map_location="cpu", weights_only=False)["step"] == 2


def test_onnx_export_matches_pytorch(one_step_checkpoint: Path, tiny_split: Path, tmp_path: Path) -> None:
    path, diff = export(one_step_checkpoint, tmp_path / "exported", check_data=tiny_split)
    assert path.exists() and path.stat().st_size < 10e6
    assert diff is not None and diff <= 1e-4


def test_training_crops_equal_the_service_batch(tiny_split: Path) -> None:
    """Un-augmented training inputs are exactly what the service's build_batch feeds the model."""
    import cv2

    from service.detector.preprocess import build_batch
    from training.coco import ANNOTATIONS_FILENAME, read_coco

    manifest = build_manifest()
    split = load_split(tiny_split, manifest, progress=False)
    rows = np.flatnonzero(split.image_index == split.image_index[0])
    inputs, *_ = make_batch(split, rows, manifest, rng=None)
    image_file = read_coco(tiny_split / ANNOTATIONS_FILENAME)["images"][split.image_index[0]]["file_name"]
    served, _ = build_batch(cv2.imread(str(tiny_split / image_file)), split.boxes[rows], manifest)
    np.testing.assert_array_equal(inputs, served)
