"""Crops from boxes, and the affine maps between image, network input and heatmap. Pixel (row r,
col c) has centre (c + 0.5, r + 0.5) in all three, so one affine per instance maps a point between
them with no half-pixel fudge at the call sites.
"""

from __future__ import annotations

import cv2
import numpy as np

_HALF = np.array([0.5, 0.5])
#: pixels beyond a crop's square that its resampling may read: the bilinear neighbour, and rounding
CONTEXT_MARGIN_PX = 2


def crop_affines(boxes: np.ndarray, padding: float, size: tuple[int, int]) -> np.ndarray:
    """Image -> crop affines ``(N, 2, 3)`` for boxes ``[x, y, w, h]``: a square centred on the box,
    side ``max(w, h) * (1 + padding)``, resized to ``size = (height, width)``."""
    centres, sides = _squares(boxes, padding)
    height, width = size
    affines = np.zeros((len(sides), 2, 3))
    affines[:, 0, 0] = width / sides
    affines[:, 1, 1] = height / sides
    affines[:, :, 2] = np.stack([width / 2.0, height / 2.0]) - affines[:, [0, 1], [0, 1]] * centres
    return affines


def _squares(boxes: np.ndarray, padding: float) -> tuple[np.ndarray, np.ndarray]:
    """Centres (N, 2) and sides (N,) of the boxes' square crops."""
    boxes = np.asarray(boxes, dtype=np.float64).reshape(-1, 4)
    return boxes[:, :2] + boxes[:, 2:] / 2, np.maximum(boxes[:, 2], boxes[:, 3]) * (1.0 + padding)


def crop_contexts(boxes: np.ndarray, padding: float, width: int, height: int) -> np.ndarray:
    """The pixels each box's crop is resampled from, ``(N, 4)`` integers ``[x0, y0, x1, y1)``: its
    square widened by ``CONTEXT_MARGIN_PX`` on every side, clipped to the ``width`` x ``height`` frame."""
    centres, sides = _squares(boxes, padding)
    halves = (sides / 2)[:, None]
    low = np.floor(centres - halves).astype(np.int64) - CONTEXT_MARGIN_PX
    high = np.ceil(centres + halves).astype(np.int64) + CONTEXT_MARGIN_PX
    size = np.array([width, height])
    return np.concatenate([np.clip(low, 0, size), np.clip(high, 0, size)], axis=1)


def rescale_affines(affines: np.ndarray, from_size: tuple[int, int], to_size: tuple[int, int]) -> np.ndarray:
    """Compose ``(N, 2, 3)`` affines with the scaling from one grid size to another."""
    scale = np.array([to_size[1] / from_size[1], to_size[0] / from_size[0]])
    return affines * scale[None, :, None]


def apply_affines(affines: np.ndarray, points: np.ndarray) -> np.ndarray:
    """Map points ``(N, ..., 2)`` through per-instance affines ``(N, 2, 3)``."""
    points = np.asarray(points, dtype=np.float64)
    shape = points.shape
    flat = points.reshape(shape[0], -1, 2)
    mapped = np.einsum("nij,nkj->nki", affines[:, :, :2], flat) + affines[:, None, :, 2]
    return mapped.reshape(shape)


def invert_affines(affines: np.ndarray) -> np.ndarray:
    """Inverse of each ``(2, 3)`` affine."""
    linear_inv = np.linalg.inv(affines[:, :, :2])
    offset = -np.einsum("nij,nj->ni", linear_inv, affines[:, :, 2])
    return np.concatenate([linear_inv, offset[:, :, None]], axis=2)


def warp_crop(image: np.ndarray, affine: np.ndarray, size: tuple[int, int]) -> np.ndarray:
    """Resample ``image`` through one continuous-coordinate affine into ``size = (h, w)``, shifted
    by half a pixel on both sides for OpenCV, which puts pixel centres at integer coordinates."""
    linear = affine[:, :2]
    offset = affine[:, 2] + linear @ _HALF - _HALF
    matrix = np.concatenate([linear, offset[:, None]], axis=1)
    border = {"borderMode": cv2.BORDER_CONSTANT, "borderValue": 0}
    return cv2.warpAffine(image, matrix, (size[1], size[0]), flags=cv2.INTER_LINEAR, **border)
