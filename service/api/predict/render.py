"""Draw a prediction response over its image: people would rather look than read."""

from __future__ import annotations

import math
from dataclasses import dataclass

import cv2
import numpy as np

from service.api.predict.predict_schemas import (
    BallSet,
    EllipseSet,
    InstanceOut,
    PredictResponse,
    UnboundedSet,
)
from service.detector.manifest import Manifest

Box = tuple[int, int, int, int]  # x0, y0, x1, y1 in pixels, x1 and y1 excluded

_FONT = cv2.FONT_HERSHEY_SIMPLEX
_SHIFT = 4  # OpenCV fixed-point bits: sub-pixel drawing
_SCALE = 1 << _SHIFT
# Ten distinct colours (BGR), one per keypoint index modulo ten.
_BGR = bytes.fromhex("4b19e6 4bb43c 19e1ff c88200 3082f5 b41e91 f0f046 e632f0 3cf5d2 bebefa")
_PALETTE = [tuple(_BGR[i : i + 3]) for i in range(0, len(_BGR), 3)]
# Labels in _PALETTE's colours, tinted toward white (by these shares) where needed to read at 7:1
# or more on their black boxes (WCAG AAA; AA asks 4.5:1, which tests/api/test_png_labels.py
# checks): the red, dark blue, purple and magenta were 4.6, 5.0, 3.0 and 6.3. Still each set's hue.
_LABEL_TINTS = {0: 0.35, 3: 0.25, 5: 0.45, 7: 0.15}
_LABEL_PALETTE = [
    tuple(round(c + (255 - c) * _LABEL_TINTS.get(i, 0.0)) for c in colour)
    for i, colour in enumerate(_PALETTE)
]


def _fixed(point: tuple[float, float]) -> tuple[int, int]:
    # Response coordinates put pixel centres at +0.5; OpenCV draws them at integers.
    return (round((point[0] - 0.5) * _SCALE), round((point[1] - 0.5) * _SCALE))


def _draw_set(canvas: np.ndarray, region, colour: tuple[int, ...], thickness: int) -> None:
    style = (colour, thickness, cv2.LINE_AA, _SHIFT)
    if isinstance(region, BallSet):
        cv2.circle(canvas, _fixed(region.center), round(min(region.radius, 1e5) * _SCALE), *style)
    elif isinstance(region, EllipseSet):
        a, b = (round(min(axis, 1e5) * _SCALE) for axis in region.semi_axes)
        cv2.ellipse(canvas, _fixed(region.center), (b, a), region.angle_deg, 0, 360, *style)


def _legend_lines(response: PredictResponse) -> list[str]:
    cal = response.calibration
    return [
        f"{cal.nonconformity} sets, {100 * (1 - cal.epsilon):g}% coverage per {cal.coverage}",
        f"epsilon {cal.epsilon:g}" + (f", PAC delta {cal.delta:g}" if cal.delta else ""),
        f"calibration v{cal.version}, model {response.model.name}",
    ]


def _legend_layout(shape: tuple[int, ...], lines: list[str]) -> tuple[float, int, Box]:
    """The legend's font scale, line height and box (top-left corner of the image)."""
    scale = max(0.4, min(shape[:2]) / 900)
    sizes = [cv2.getTextSize(text, _FONT, scale, 1)[0] for text in lines]
    line_height = max(h for _, h in sizes) * 2
    return scale, line_height, (0, 0, max(w for w, _ in sizes) + 12, line_height * len(lines) + 6)


def _draw_legend(canvas: np.ndarray, response: PredictResponse) -> None:
    lines = _legend_lines(response)
    scale, line_height, box = _legend_layout(canvas.shape, lines)
    cv2.rectangle(canvas, box[:2], box[2:], (0, 0, 0), -1)
    for row, text in enumerate(lines):
        cv2.putText(canvas, text, (6, line_height * (row + 1)), _FONT, scale, (255, 255, 255), 1, cv2.LINE_AA)


_AXIS_COLOURS = [(0, 0, 255), (0, 255, 0), (255, 0, 0)]  # x red, y green, z blue (BGR)
_BOX_EDGES = [(a, b) for a in range(8) for b in range(a + 1, 8) if bin(a ^ b).count("1") == 1]


def _draw_pose(canvas: np.ndarray, instance: InstanceOut, camera: np.ndarray, manifest: Manifest) -> None:
    """The estimated pose's projected 3D box (around the object's 3D keypoints) and its axes."""
    pose = instance.pose
    points_3d = manifest.object(instance.object).keypoints_3d
    if pose is None or pose.rotation is None or pose.translation is None or not points_3d:
        return
    low, high = np.min(points_3d, axis=0), np.max(points_3d, axis=0)
    corners = np.array([[(high if (k >> d) & 1 else low)[d] for d in range(3)] for k in range(8)])
    axis = 0.5 * float(np.max(high - low))
    axes = np.array([[0.0, 0.0, 0.0], [axis, 0, 0], [0, axis, 0], [0, 0, axis]])
    camera_points = np.vstack([corners, axes]) @ np.array(pose.rotation).T + np.array(pose.translation)
    if (camera_points[:, 2] <= 0).any():
        return  # a box reaching behind the camera has no faithful drawing
    image_points = [_fixed(tuple(p[:2] / p[2])) for p in camera_points @ camera.T]
    for a, b in _BOX_EDGES:
        cv2.line(canvas, image_points[a], image_points[b], (255, 255, 255), 1, cv2.LINE_AA, _SHIFT)
    for tip, colour in zip(image_points[9:], _AXIS_COLOURS, strict=True):  # from the origin, image_points[8]
        cv2.line(canvas, image_points[8], tip, colour, 2, cv2.LINE_AA, _SHIFT)


@dataclass(frozen=True)
class Label:
    """A keypoint's name, where it is drawn, and the keypoint it names."""

    text: str
    box: Box
    keypoint: tuple[int, int]
    colour: tuple[int, int, int]


def _font_scale(shape: tuple[int, ...]) -> float:
    return max(0.4, min(shape[:2]) / 1200)


def layout_labels(shape: tuple[int, ...], response: PredictResponse) -> list[Label]:
    """Every keypoint's label, placed where it hides no other label, no keypoint, no small set
    and not the legend: the free place nearest its keypoint (a line joins them when apart)."""
    scale = _font_scale(shape)
    keypoints = [keypoint for instance in response.instances for keypoint in instance.keypoints]
    points = [(int(k.point[0]), int(k.point[1])) for k in keypoints]
    taken = [_legend_layout(shape, _legend_lines(response))[2]]
    taken += [_set_box(k.set, point) for k, point in zip(keypoints, points, strict=True)]
    labels = []
    for keypoint, point in zip(keypoints, points, strict=True):
        text = keypoint.name + (" (unbounded)" if keypoint.set.type == "unbounded" else "")
        (width, height), baseline = cv2.getTextSize(text, _FONT, scale, 1)
        box = _free_place(shape, point, (width + 4, height + baseline + 4), np.array(taken))
        taken.append(box)
        labels.append(Label(text, box, point, _LABEL_PALETTE[keypoint.index % len(_LABEL_PALETTE)]))
    return labels


_MARK = 4  # half the side of a keypoint's cross
_SMALL_SET = 40  # sets with a semi-axis up to this many pixels are kept clear of labels
_DIRECTIONS = np.deg2rad(np.arange(0, 360, 22.5))
_RADII = np.array([3, 8, 14, 22, 32, 45, 60, 80, 105, 135, 170, 210, 260, 320, 400])


def _set_box(region, point: tuple[int, int]) -> Box:
    size = region.radius if isinstance(region, BallSet) else max(getattr(region, "semi_axes", [math.inf]))
    reach = max(_MARK, math.ceil(size)) if size <= _SMALL_SET else _MARK
    x, y = point if isinstance(region, UnboundedSet) else (int(region.center[0]), int(region.center[1]))
    return (x - reach, y - reach, x + reach + 1, y + reach + 1)


def _free_place(
    shape: tuple[int, ...], point: tuple[int, int], size: tuple[int, int], taken: np.ndarray
) -> Box:
    """The box of ``size`` nearest ``point`` (rings of directions) inside the image and clear of
    ``taken``; the nearest inside when none is clear (a picture too small for its labels)."""
    width, height = size
    radius, angle = np.meshgrid(_RADII, _DIRECTIONS, indexing="ij")
    radius, angle = radius.ravel(), angle.ravel()
    x0 = np.round(point[0] + np.cos(angle) * (radius + width / 2) - width / 2).astype(int)
    y0 = np.round(point[1] + np.sin(angle) * (radius + height / 2) - height / 2).astype(int)
    x0 = np.clip(x0, 0, max(0, shape[1] - width))
    y0 = np.clip(y0, 0, max(0, shape[0] - height))
    boxes = np.stack([x0, y0, x0 + width, y0 + height], axis=1)
    # Boxes of positive size overlap where the larger start is below the smaller end, in x and in y.
    b, t = boxes[:, None], taken[None]
    overlaps = (
        (np.maximum(b[..., :2], t[..., :2]) < np.minimum(b[..., 2:], t[..., 2:])).all(axis=2).any(axis=1)
    )
    free = np.flatnonzero(~overlaps)
    return tuple(int(v) for v in boxes[free[0] if free.size else 0])


def _draw_labels(canvas: np.ndarray, labels: list[Label]) -> None:
    """Lines from keypoints to their labels first, then the labels over every line."""
    for label in labels:
        x0, y0, x1, y1 = label.box
        nearest = (min(max(label.keypoint[0], x0), x1 - 1), min(max(label.keypoint[1], y0), y1 - 1))
        if abs(nearest[0] - label.keypoint[0]) + abs(nearest[1] - label.keypoint[1]) > _MARK + 2:
            cv2.line(canvas, label.keypoint, nearest, label.colour, 1, cv2.LINE_AA)
    scale = _font_scale(canvas.shape)
    for label in labels:
        x0, y0, x1, y1 = label.box
        cv2.rectangle(canvas, (x0, y0), (x1 - 1, y1 - 1), (0, 0, 0), -1)
        (_, height), _ = cv2.getTextSize(label.text, _FONT, scale, 1)
        cv2.putText(canvas, label.text, (x0 + 2, y0 + 2 + height), _FONT, scale, label.colour, 1, cv2.LINE_AA)


def render_prediction(
    image_bgr: np.ndarray,
    response: PredictResponse,
    camera: np.ndarray | None = None,
    manifest: Manifest | None = None,
) -> bytes:
    """PNG bytes of the image with every set, point estimate and keypoint name drawn on it; with a
    camera matrix and the manifest, each instance's estimated pose too."""
    canvas = cv2.cvtColor(image_bgr, cv2.COLOR_GRAY2BGR) if image_bgr.ndim == 2 else image_bgr.copy()
    thickness = max(1, round(min(canvas.shape[:2]) / 400))
    for instance in response.instances:
        x, y, w, h = instance.bbox
        cv2.rectangle(canvas, _fixed((x, y)), _fixed((x + w, y + h)), (200, 200, 200), 1, cv2.LINE_AA, _SHIFT)
        if camera is not None and manifest is not None:
            _draw_pose(canvas, instance, camera, manifest)
        for keypoint in instance.keypoints:
            colour = _PALETTE[keypoint.index % len(_PALETTE)]
            _draw_set(canvas, keypoint.set, colour, thickness)
            px, py = int(keypoint.point[0]), int(keypoint.point[1])
            cv2.drawMarker(canvas, (px, py), colour, cv2.MARKER_CROSS, 2 * _MARK - 2, 1)
    _draw_labels(canvas, layout_labels(canvas.shape, response))
    _draw_legend(canvas, response)
    ok, png = cv2.imencode(".png", canvas)
    if not ok:
        raise RuntimeError("PNG encoding failed")
    return png.tobytes()
