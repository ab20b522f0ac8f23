"""Training crops from a COCO keypoints split, cut with the service's own crop code.

Crops are cut exactly as ``service.detector.preprocess.build_batch`` does (same
affines, same resampling, same normalization); augmentation only perturbs the boxes
before ``crop_affines`` and the uint8 crop pixels before normalization.
"""

from __future__ import annotations

from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
from tqdm import tqdm

from service.detector.crop import apply_affines, crop_affines, rescale_affines, warp_crop
from service.detector.manifest import Manifest
from service.detector.preprocess import normalize_crops, to_model_colour
from training.coco import ANNOTATIONS_FILENAME, read_coco
from training.keypoints3d import KEYPOINTS_PER_OBJECT

SIGMA = 1.5  # heatmap pixels


@dataclass
class Split:
    """Decoded images (model colour order) and one row per annotated instance."""

    images: list[np.ndarray]
    image_index: np.ndarray  # (N,)
    category: np.ndarray  # (N,) 0-based object class
    boxes: np.ndarray  # (N, 4) x, y, w, h
    keypoints: np.ndarray  # (N, 8, 3) x, y, v

    def __len__(self) -> int:
        return len(self.category)


def load_split(
    folder: Path, manifest: Manifest, max_images: int | None = None, progress: bool = True
) -> Split:
    coco = read_coco(Path(folder) / ANNOTATIONS_FILENAME)
    entries = coco["images"][:max_images] if max_images else coco["images"]
    slot = {im["id"]: i for i, im in enumerate(entries)}
    images = []
    for im in tqdm(entries, desc=f"load {folder}", disable=not progress, mininterval=10):
        bgr = cv2.imread(str(Path(folder) / im["file_name"]), cv2.IMREAD_COLOR)
        images.append(np.ascontiguousarray(to_model_colour(bgr, manifest.input)))
    anns = [a for a in coco["annotations"] if a["image_id"] in slot]
    return Split(
        images=images,
        image_index=np.array([slot[a["image_id"]] for a in anns], dtype=np.int64),
        category=np.array([a["category_id"] - 1 for a in anns], dtype=np.int64),
        boxes=np.array([a["bbox"] for a in anns], dtype=np.float64).reshape(-1, 4),
        keypoints=np.array([a["keypoints"] for a in anns], dtype=np.float64).reshape(
            -1, KEYPOINTS_PER_OBJECT, 3
        ),
    )


def jitter_boxes(
    rng: np.random.Generator, boxes: np.ndarray, shift: float = 0.06, scale: float = 0.1
) -> np.ndarray:
    """Shift box centres by N(0, shift * side) and scale each side by exp(N(0, scale))."""
    side = np.maximum(boxes[:, 2], boxes[:, 3])[:, None]
    centre = boxes[:, :2] + boxes[:, 2:] / 2 + rng.normal(0, shift, (len(boxes), 2)) * side
    size = boxes[:, 2:] * np.exp(rng.normal(0, scale, (len(boxes), 2)))
    return np.concatenate([centre - size / 2, size], axis=1)


def cut_crops(
    split: Split, rows: np.ndarray, boxes: np.ndarray, manifest: Manifest
) -> tuple[np.ndarray, np.ndarray]:
    """uint8 crops ``(B, H, W, C)`` and image->heatmap affines, as ``build_batch`` cuts them."""
    spec = manifest.input
    size = (spec.height, spec.width)
    affines = crop_affines(boxes, manifest.crop.padding, size)
    crops = np.empty((len(rows), spec.height, spec.width, spec.channels), dtype=np.uint8)
    for i, (row, affine) in enumerate(zip(rows, affines, strict=True)):
        crops[i] = warp_crop(split.images[split.image_index[row]], affine, size).reshape(crops.shape[1:])
    return crops, rescale_affines(affines, size, (manifest.output.height, manifest.output.width))


def colour_jitter(rng: np.random.Generator, crops: np.ndarray) -> np.ndarray:
    n = len(crops)
    x = crops.astype(np.float32)
    gain = rng.uniform(0.75, 1.25, (n, 1, 1, 1)) * rng.uniform(0.9, 1.1, (n, 1, 1, 3))
    mean = x.mean(axis=(1, 2, 3), keepdims=True)
    x = (x - mean) * gain + mean + rng.uniform(-25, 25, (n, 1, 1, 1))
    x += rng.normal(0, 1, x.shape).astype(np.float32) * rng.uniform(0, 6, (n, 1, 1, 1)).astype(np.float32)
    return x.clip(0, 255).astype(np.uint8)


def cutout(rng: np.random.Generator, crops: np.ndarray, prob: float = 0.5) -> np.ndarray:
    """Occlusion augmentation: up to two random rectangles of flat colour or noise."""
    h, w = crops.shape[1:3]
    for crop in crops:
        for _ in range(int(rng.random() < prob) + int(rng.random() < prob / 3)):
            rh, rw = (rng.uniform(0.15, 0.5, 2) * (h, w)).astype(int)
            y, x = rng.integers(0, h - rh), rng.integers(0, w - rw)
            fill = rng.integers(0, 256, (rh, rw, 3)) if rng.random() < 0.5 else rng.integers(0, 256, 3)
            crop[y : y + rh, x : x + rw] = fill
    return crops


def gaussian_targets(points: np.ndarray, height: int, width: int, sigma: float = SIGMA) -> np.ndarray:
    """``(B, K, 2)`` continuous heatmap coordinates -> ``(B, K, H, W)`` Gaussians.

    The Gaussian centre in array-index terms is ``(u - 0.5, v - 0.5)`` because pixel
    (row r, col c) has centre (c + 0.5, r + 0.5).
    """
    cols = np.arange(width, dtype=np.float32)
    rows = np.arange(height, dtype=np.float32)
    gx = np.exp(-((cols - (points[..., 0:1] - 0.5)) ** 2) / (2 * sigma**2))
    gy = np.exp(-((rows - (points[..., 1:2] - 0.5)) ** 2) / (2 * sigma**2))
    return (gy[..., :, None] * gx[..., None, :]).astype(np.float32)


def make_batch(
    split: Split, rows: np.ndarray, manifest: Manifest, rng: np.random.Generator | None
) -> tuple[np.ndarray, np.ndarray, np.ndarray, np.ndarray]:
    """Network inputs, targets ``(B, 8, H, W)`` for the instance's own channels, those channels,
    and the keypoints in continuous heatmap coordinates ``(B, 8, 2)``."""
    boxes = split.boxes[rows]
    if rng is not None:
        boxes = jitter_boxes(rng, boxes)
    crops, affines = cut_crops(split, rows, boxes, manifest)
    if rng is not None:
        crops = cutout(rng, colour_jitter(rng, crops))
    points = apply_affines(affines, split.keypoints[rows, :, :2])
    targets = gaussian_targets(points, manifest.output.height, manifest.output.width)
    channels = split.category[rows, None] * KEYPOINTS_PER_OBJECT + np.arange(KEYPOINTS_PER_OBJECT)
    return normalize_crops(crops, manifest.input), targets, channels, points.astype(np.float32)
