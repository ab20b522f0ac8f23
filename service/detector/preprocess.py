"""An image and its boxes -> the network's input batch, as the manifest says. Crops are cut from
the image as decoded and converted to the model's colour order afterwards (reordering commutes
with the per-channel resampling; only the crops' pixels are touched).
"""

from __future__ import annotations

import cv2
import numpy as np

from service.detector.crop import crop_affines, rescale_affines
from service.detector.frames import ImageSource
from service.detector.manifest import InputSpec, Manifest


def to_model_colour(pixels: np.ndarray, spec: InputSpec) -> np.ndarray:
    """Channels-last pixels ``(..., H, W, 1 or 3)`` in OpenCV order (gray or BGR) -> model order."""
    gray = pixels.shape[-1] == 1
    if spec.color == "GRAY":
        if gray:
            return pixels
        rows = np.ascontiguousarray(pixels).reshape(-1, pixels.shape[-2], 3)  # images stacked vertically
        return cv2.cvtColor(rows, cv2.COLOR_BGR2GRAY).reshape(*pixels.shape[:-1], 1)
    if gray:
        return np.repeat(pixels, 3, axis=-1)
    return pixels[..., ::-1] if spec.color == "RGB" else pixels


def normalize_crops(crops: np.ndarray, spec: InputSpec) -> np.ndarray:
    """``(N, H, W, C)`` uint8 crops in model colour order -> ``(N, C, H, W)`` float32 input."""
    mean = np.asarray(spec.mean, dtype=np.float32)
    std = np.asarray(spec.std, dtype=np.float32)
    batch = np.ascontiguousarray(crops.transpose(0, 3, 1, 2), dtype=np.float32)
    batch /= np.float32(spec.scale)
    batch -= mean[:, None, None]
    batch /= std[:, None, None]
    return batch


def build_batch(
    image: np.ndarray | ImageSource, boxes: np.ndarray, manifest: Manifest
) -> tuple[np.ndarray, np.ndarray]:
    """Crop every box of ``image`` (BGR or gray pixels, or a source: the whole frame or regions)
    and return ``(input batch NCHW float32, image->heatmap affines (N, 2, 3))``."""
    spec = manifest.input
    input_size = (spec.height, spec.width)
    affines = crop_affines(boxes, manifest.crop.padding, input_size)
    source = image if isinstance(image, ImageSource) else ImageSource.whole(image)
    crops = source.crops(affines, input_size)
    heatmap_affines = rescale_affines(affines, input_size, (manifest.output.height, manifest.output.width))
    return normalize_crops(to_model_colour(crops, spec), spec), heatmap_affines
