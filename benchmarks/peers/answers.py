"""Before timing: every peer must give the service's answer (centres and shape matrices)."""

from __future__ import annotations

import json
import urllib.request

import numpy as np

TOLERANCE = 1e-6
#: on a GPU the convolution algorithms cuDNN picks differ with the batch size (fp32, TF32 off:
#: heatmaps within about 1e-6 of each other, relative), so merged runs move the sets a little
GPU_TOLERANCE = 1e-4


def post(url: str, body: bytes, content_type: str) -> dict:
    request = urllib.request.Request(
        f"{url}/v1/predict", data=body, headers={"Content-Type": content_type, "Accept": "application/json"}
    )
    with urllib.request.urlopen(request, timeout=60) as response:
        return json.loads(response.read())


def _set_shape(region: dict) -> list[list[float]]:
    """The service's set as its shape matrix L ((y - c)^T L (y - c) <= 1; zeros = unbounded)."""
    if region["type"] == "ellipse":
        return region["shape_matrix"]
    if region["type"] == "ball":
        inverse = 1 / region["radius"] ** 2 if region["radius"] > 0 else 0.0
        return [[inverse, 0.0], [0.0, inverse]]
    return [[0.0, 0.0], [0.0, 0.0]]


def sets_of(answer: dict) -> tuple[np.ndarray, np.ndarray]:
    """``(centres (M, 2), shapes (M, 2, 2))`` of a service or peer answer, keypoints in order."""
    keypoints = [kp for instance in answer["instances"] for kp in instance["keypoints"]]
    centers = np.array([kp["point"] for kp in keypoints], dtype=np.float64)
    shapes = [kp["shape_matrix"] if "shape_matrix" in kp else _set_shape(kp["set"]) for kp in keypoints]
    return centers, np.array(shapes, dtype=np.float64).reshape(-1, 2, 2)


def difference(service: dict, peer: dict, tolerance: float = TOLERANCE) -> str | None:
    """None when the answers agree within ``tolerance``, else why not: centres in pixels, shape
    matrices (entries of 1e-3 to 1 px^-2) relative to their largest entry."""
    (c1, s1), (c2, s2) = sets_of(service), sets_of(peer)
    if c1.shape != c2.shape:
        return f"{len(c1)} keypoints from the service, {len(c2)} from the peer"
    centres = float(np.abs(c1 - c2).max(initial=0.0))
    if centres > tolerance:
        return f"centres differ by {centres:.2e} px"
    scale = max(float(np.abs(s1).max(initial=0.0)), 1e-300)
    shapes = float(np.abs(s1 - s2).max(initial=0.0)) / scale
    if shapes > tolerance:
        return f"shape matrices differ by {shapes:.2e} (relative to their largest entry)"
    return None
