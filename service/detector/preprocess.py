"""Turn an image and its boxes into the network's input batch, exactly as the manifest says."""

from __future__ import annotations

import cv2
import numpy as np

from service.detector.crop import crop_affines, rescale_affines, warp_crop
from service.detector.manifest import InputSpec, Manifest


def to_model_colour(image_bgr: np.ndarray, spec: InputSpec) -> np.ndarray:
    """Convert a decoded OpenCV image (BGR, or single-channel gray) to the model's colour order."""
    if image_bgr.ndim == 2:
        image_bgr = image_bgr[:, :, None]
    gray = image_bgr.shape[2] == 1
    if spec.color == "GRAY":
        return image_bgr if gray else cv2.cvtColor(image_bgr, cv2.COLOR_BGR2GRAY)[:, :, None]
    if gray:
        image_bgr = np.repeat(image_bgr, 3, axis=2)
    return image_bgr[:, :, ::-1] if spec.color == "RGB" else image_bgr


def normalize_crops(crops: np.ndarray, spec: InputSpec) -> np.ndarray:
    """``(N, H, W, C)`` uint8 crops -> ``(N, C, H, W)`` float32 network input."""
    mean = np.asarray(spec.mean, dtype=np.float32)
    std = np.asarray(spec.std, dtype=np.float32)
    batch = (crops.astype(np.float32) / np.float32(spec.scale) - mean) / std
    return np.ascontiguousarray(batch.transpose(0, 3, 1, 2))


def build_batch(
    image_bgr: np.ndarray, boxes: np.ndarray, manifest: Manifest
) -> tuple[np.ndarray, np.ndarray]:
    """Crop every box and return ``(input batch NCHW float32, image->heatmap affines (N, 2, 3))``."""
    spec = manifest.input
    input_size = (spec.height, spec.width)
    affines = crop_affines(boxes, manifest.crop.padding, input_size)
    image = to_model_colour(image_bgr, spec)
    crops = np.empty((len(affines), spec.height, spec.width, spec.channels), dtype=np.uint8)
    for i, affine in enumerate(affines):
        crops[i] = warp_crop(image, affine, input_size).reshape(spec.height, spec.width, -1)
    heatmap_affines = rescale_affines(affines, input_size, (manifest.output.height, manifest.output.width))
    return normalize_crops(crops, spec), heatmap_affines
