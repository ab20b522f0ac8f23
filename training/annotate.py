"""COCO keypoint annotations for a rendered scene: projections, visibility, full boxes, poses.

Every keypoint is labelled (as in LM-O): COCO v=2 when it passes the depth-buffer
test (the rendered surface at its pixel is this object, at its depth), v=1 when it is
occluded, self-occluded or outside the image. The box is the full projected box of the
mesh, clipped to the image, so occluded objects keep a sensible crop.
"""

from __future__ import annotations

from dataclasses import dataclass

import cv2
import numpy as np

from training.camera import Camera
from training.keypoints3d import class_keypoints
from training.objects import OBJECT_CLASSES, class_mesh
from training.scene import Placed, Rendered

MIN_BOX_SIDE = 20.0
MIN_INSIDE_FRACTION = 0.5
MIN_VISIB_FRACT = 0.1


@dataclass(frozen=True)
class Limits:
    min_box_side: float = MIN_BOX_SIDE
    min_inside_fraction: float = MIN_INSIDE_FRACTION
    min_visib_fract: float = MIN_VISIB_FRACT


def _silhouette_pixels(camera: Camera, vertices_cam: np.ndarray, faces: np.ndarray) -> int:
    """Pixel count of the unoccluded silhouette, by rasterizing every projected triangle."""
    uv = camera.project(vertices_cam) - 0.5  # OpenCV puts pixel centres at integers
    mask = np.zeros((camera.height, camera.width), dtype=np.uint8)
    tris = np.round(uv[faces] * 16).astype(np.int32)
    for tri in tris:  # fillPoly on many polygons uses even-odd filling; triangles overlap
        cv2.fillConvexPoly(mask, tri, 1, lineType=cv2.LINE_8, shift=4)
    return int(mask.sum())


def _visibility(rendered: Rendered, body: int, uv: np.ndarray, z: np.ndarray, tol: float) -> np.ndarray:
    """COCO flags: 2 if the rendered surface near the keypoint pixel is this body at its depth."""
    h, w = rendered.seg.shape
    flags = np.ones(len(uv), dtype=np.int64)
    for k, ((x, y), depth) in enumerate(zip(uv, z, strict=True)):
        if not (0 <= x < w and 0 <= y < h):
            continue
        c, r = int(x), int(y)
        rows, cols = slice(max(r - 1, 0), r + 2), slice(max(c - 1, 0), c + 2)
        hit = (rendered.seg[rows, cols] == body) & (np.abs(rendered.depth[rows, cols] - depth) < tol)
        flags[k] = 2 if hit.any() else 1
    return flags


def _box(uv: np.ndarray, width: int, height: int) -> tuple[np.ndarray, float]:
    """Clipped ``[x, y, w, h]`` box and the fraction of the unclipped box inside the image."""
    lo, hi = uv.min(0), uv.max(0)
    full = float(np.prod(hi - lo))
    clo, chi = np.maximum(lo, 0), np.minimum(hi, [width, height])
    size = np.maximum(chi - clo, 0)
    return np.r_[clo, size], float(np.prod(size)) / max(full, 1e-9)


def annotate_object(rendered: Rendered, obj: Placed, limits: Limits = Limits()) -> dict | None:
    """One COCO annotation (without ids) for a placed object, or None if it is unusable."""
    camera, mesh = rendered.camera, class_mesh(OBJECT_CLASSES[obj.class_index])
    rot = camera.rotation @ obj.rotation
    trans = camera.rotation @ obj.position + camera.translation
    verts = mesh.vertices @ rot.T + trans
    if verts[:, 2].min() <= camera.near:
        return None
    box, inside = _box(camera.project(verts), camera.width, camera.height)
    if min(box[2], box[3]) < limits.min_box_side or inside < limits.min_inside_fraction:
        return None
    visible = int((rendered.seg == obj.body).sum())
    visib_fract = min(1.0, visible / max(_silhouette_pixels(camera, verts, mesh.faces), 1))
    if visib_fract < limits.min_visib_fract:
        return None
    kps_cam = class_keypoints(obj.class_index) @ rot.T + trans
    uv = camera.project(kps_cam)
    flags = _visibility(rendered, obj.body, uv, kps_cam[:, 2], tol=max(0.005, 0.04 * mesh.diameter))
    return {
        "category_id": obj.class_index + 1,
        "bbox": [round(float(v), 3) for v in box],
        "keypoints": [
            v
            for (x, y), f in zip(uv, flags, strict=True)
            for v in (round(float(x), 3), round(float(y), 3), int(f))
        ],
        "num_keypoints": len(flags),
        "area": float(visible),
        "iscrowd": 0,
        "visib_fract": round(visib_fract, 4),
        "cam_K": camera.intrinsics.tolist(),
        "cam_R_m2c": rot.tolist(),
        "cam_t_m2c": (trans * 1000.0).tolist(),  # millimetres, like BOP
    }


def annotate_scene(rendered: Rendered, limits: Limits = Limits()) -> list[dict]:
    anns = [annotate_object(rendered, obj, limits) for obj in rendered.objects]
    return [a for a in anns if a is not None]
