"""Draw a prediction response over its image: people would rather look than read."""

from __future__ import annotations

import cv2
import numpy as np

from service.api.predict_schemas import BallSet, EllipseSet, InstanceOut, PredictResponse
from service.detector.manifest import Manifest

_SHIFT = 4  # OpenCV fixed-point bits: sub-pixel drawing
_SCALE = 1 << _SHIFT
_PALETTE = [
    (75, 25, 230),
    (75, 180, 60),
    (25, 225, 255),
    (200, 130, 0),
    (48, 130, 245),
    (180, 30, 145),
    (240, 240, 70),
    (230, 50, 240),
    (60, 245, 210),
    (190, 190, 250),
]


def _fixed(point: tuple[float, float]) -> tuple[int, int]:
    # Response coordinates put pixel centres at +0.5; OpenCV draws them at integers.
    return (round((point[0] - 0.5) * _SCALE), round((point[1] - 0.5) * _SCALE))


def _draw_set(canvas: np.ndarray, region, colour: tuple[int, int, int], thickness: int) -> None:
    if isinstance(region, BallSet):
        radius = min(region.radius, 1e5)
        cv2.circle(
            canvas, _fixed(region.center), round(radius * _SCALE), colour, thickness, cv2.LINE_AA, _SHIFT
        )
    elif isinstance(region, EllipseSet):
        a, b = (min(axis, 1e5) for axis in region.semi_axes)
        axes = (round(b * _SCALE), round(a * _SCALE))
        cv2.ellipse(
            canvas,
            _fixed(region.center),
            axes,
            region.angle_deg,
            0,
            360,
            colour,
            thickness,
            cv2.LINE_AA,
            _SHIFT,
        )


def _draw_legend(canvas: np.ndarray, response: PredictResponse) -> None:
    cal = response.calibration
    lines = [
        f"{cal.nonconformity} sets, {100 * (1 - cal.epsilon):g}% coverage per {cal.coverage}",
        f"epsilon {cal.epsilon:g}" + (f", PAC delta {cal.delta:g}" if cal.delta else ""),
        f"calibration v{cal.version}, model {response.model.name}",
    ]
    scale = max(0.4, min(canvas.shape[:2]) / 900)
    sizes = [cv2.getTextSize(text, cv2.FONT_HERSHEY_SIMPLEX, scale, 1)[0] for text in lines]
    line_height = max(h for _, h in sizes) * 2
    width = max(w for w, _ in sizes) + 12
    cv2.rectangle(canvas, (0, 0), (width, line_height * len(lines) + 6), (0, 0, 0), -1)
    for row, text in enumerate(lines):
        origin = (6, line_height * (row + 1))
        cv2.putText(canvas, text, origin, cv2.FONT_HERSHEY_SIMPLEX, scale, (255, 255, 255), 1, cv2.LINE_AA)


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
    rotation, translation = np.array(pose.rotation), np.array(pose.translation)
    camera_points = np.vstack([corners, axes]) @ rotation.T + translation
    if (camera_points[:, 2] <= 0).any():
        return  # a box reaching behind the camera has no faithful drawing
    projected = camera_points @ camera.T
    image_points = [_fixed(tuple(p[:2] / p[2])) for p in projected]
    for a, b in _BOX_EDGES:
        cv2.line(canvas, image_points[a], image_points[b], (255, 255, 255), 1, cv2.LINE_AA, _SHIFT)
    origin = image_points[8]
    for tip, colour in zip(image_points[9:], _AXIS_COLOURS, strict=True):
        cv2.line(canvas, origin, tip, colour, 2, cv2.LINE_AA, _SHIFT)


def render_prediction(
    image_bgr: np.ndarray,
    response: PredictResponse,
    camera: np.ndarray | None = None,
    manifest: Manifest | None = None,
) -> bytes:
    """PNG bytes of the image with every set, point estimate and keypoint name drawn on it.

    With a camera matrix and the manifest, each instance's estimated pose is drawn too."""
    canvas = cv2.cvtColor(image_bgr, cv2.COLOR_GRAY2BGR) if image_bgr.ndim == 2 else image_bgr.copy()
    thickness = max(1, round(min(canvas.shape[:2]) / 400))
    font_scale = max(0.35, min(canvas.shape[:2]) / 1400)
    for instance in response.instances:
        x, y, w, h = instance.bbox
        cv2.rectangle(canvas, _fixed((x, y)), _fixed((x + w, y + h)), (200, 200, 200), 1, cv2.LINE_AA, _SHIFT)
        if camera is not None and manifest is not None:
            _draw_pose(canvas, instance, camera, manifest)
        for keypoint in instance.keypoints:
            colour = _PALETTE[keypoint.index % len(_PALETTE)]
            _draw_set(canvas, keypoint.set, colour, thickness)
            px, py = int(keypoint.point[0]), int(keypoint.point[1])
            cv2.drawMarker(canvas, (px, py), colour, cv2.MARKER_CROSS, 6, 1)
            label = keypoint.name + (" (unbounded)" if keypoint.set.type == "unbounded" else "")
            anchor = (px + 4, py - 4)
            cv2.putText(canvas, label, anchor, cv2.FONT_HERSHEY_SIMPLEX, font_scale, colour, 1, cv2.LINE_AA)
    _draw_legend(canvas, response)
    ok, png = cv2.imencode(".png", canvas)
    if not ok:
        raise RuntimeError("PNG encoding failed")
    return png.tobytes()
