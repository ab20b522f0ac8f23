"""Qualitative examples like the paper's Fig. 4: one easy and one hard instance per function.

The detector is run again on the two instances and the sets come straight from the
service's ``calibrated_sets`` (the prediction path); the largest difference to the
report's cached sets is returned, as a check of the cache.
"""

from __future__ import annotations

from pathlib import Path

import cv2
import numpy as np
from matplotlib.patches import Ellipse

from service.calibration.coco import load_coco_batch
from service.conformal import ellipse_axes, normalize_heatmaps
from service.detector.runtime import Detector
from service.image_decoding import decode_image
from service.prediction import calibrated_sets
from training.evidence.analysis import MAIN_EPSILON, Evidence
from training.evidence.figures import KINDS, plt, save
from training.evidence.inference import MAX_IMAGE_PIXELS
from training.evidence.sets import score_table, thresholds

CROP_MARGIN = 0.25


def overlay_figure(evidence: Evidence, detector: Detector, test_dir: Path, path: Path) -> tuple[Path, float]:
    """Draw the figure; also return max |sets from calibrated_sets - cached sets|."""
    manifest = detector.manifest
    batch = load_coco_batch(test_dir, manifest)
    by_annotation = {inst.annotation_id: inst for inst in batch.instances}
    table = score_table(evidence.calibration, manifest)
    figure, axes = plt.subplots(3, 2, figsize=(9, 12), squeeze=False)
    worst = 0.0
    for col, (instance, title) in enumerate(zip(evidence.overlay_instances, ("easy", "hard"), strict=True)):
        rows = np.flatnonzero(evidence.test.instance == instance)
        labeled = by_annotation[int(evidence.test.annotation_id[rows[0]])]
        image = decode_image(batch.images[labeled.image_id].path.read_bytes(), MAX_IMAGE_PIXELS)
        result = detector.infer(image, labeled.bbox[None], [labeled.object_name])
        for row, kind in enumerate(KINDS):
            values = thresholds(table, manifest, kind, MAIN_EPSILON).values
            sets = calibrated_sets(result, kind, values, manifest.heatmap)
            cached = evidence.sets[(kind, MAIN_EPSILON)]
            worst = max(
                worst, _difference(sets.centers, sets.shapes, cached.centers[rows], cached.shapes[rows])
            )
            fraction = evidence.test.visib_fract[rows[0]]
            _panel(axes[row, col], image, result, sets, labeled, manifest.heatmap)
            axes[row, col].set_title(
                f"ICP-{kind.capitalize()}, {title}: {labeled.object_name}, visib_fract {fraction:.2f}",
                fontsize=9,
            )
    figure.tight_layout()
    return save(figure, path), worst


def _difference(centers: np.ndarray, shapes: np.ndarray, cached_centers: np.ndarray, cached_shapes) -> float:
    finite = np.isfinite(shapes) & np.isfinite(cached_shapes)
    scale = np.maximum(np.abs(shapes[finite]), 1e-12)
    return float(
        max(
            np.abs(centers - cached_centers).max(),
            (np.abs(shapes[finite] - cached_shapes[finite]) / scale).max(),
        )
    )


def _panel(ax, image: np.ndarray, result, sets, instance, heatmap_spec) -> None:
    x0, y0, x1, y1 = _crop_box(instance.bbox, image.shape)
    rgb = image[y0:y1, x0:x1, ::-1]
    ax.imshow(rgb, extent=(x0, x1, y1, y0))
    heat = _heatmap_overlay(result, heatmap_spec, image.shape)[y0:y1, x0:x1]
    ax.imshow(heat, extent=(x0, x1, y1, y0), cmap="inferno", alpha=0.35 * (heat > 0.05 * heat.max()))
    a, b, angle = ellipse_axes(sets.shapes)
    colors = plt.cm.tab10(np.arange(len(a)) % 10)
    for center, semi_minor, semi_major, theta, color in zip(sets.centers, a, b, angle, colors, strict=True):
        if np.isfinite(semi_major):
            ax.add_patch(
                Ellipse(center, 2 * semi_major, 2 * semi_minor, angle=theta, fill=False, color=color, lw=1.2)
            )
    truth = instance.keypoints
    ax.scatter(
        truth[:, 0], truth[:, 1], marker="s", s=22, facecolors="none", edgecolors=colors, linewidths=1.2
    )
    ax.set_xlim(x0, x1)
    ax.set_ylim(y1, y0)
    ax.set_xticks([])
    ax.set_yticks([])


def _crop_box(bbox: np.ndarray, shape: tuple[int, ...]) -> tuple[int, int, int, int]:
    x, y, w, h = bbox
    margin = CROP_MARGIN * max(w, h)
    height, width = shape[:2]
    x0, y0 = int(max(0, np.floor(x - margin))), int(max(0, np.floor(y - margin)))
    x1, y1 = int(min(width, np.ceil(x + w + margin))), int(min(height, np.ceil(y + h + margin)))
    return x0, y0, x1, y1


def _heatmap_overlay(result, heatmap_spec, shape: tuple[int, ...]) -> np.ndarray:
    """Max over keypoints of the normalized heatmaps, resampled into image pixels."""
    probabilities = normalize_heatmaps(result.heatmaps, heatmap_spec.normalization, heatmap_spec.temperature)
    combined = probabilities.max(axis=0).astype(np.float32)
    affine = result.affines[0].copy()
    affine[:, 2] += affine[:, :2] @ np.array([0.5, 0.5]) - 0.5  # pixel centres at c + 0.5 on both sides
    flags = cv2.INTER_LINEAR | cv2.WARP_INVERSE_MAP
    return cv2.warpAffine(combined, affine, (shape[1], shape[0]), flags=flags, borderValue=0.0)
