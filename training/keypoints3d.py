"""Semantic 3D keypoints: farthest-point sampling on the mesh surface, deterministic."""

from __future__ import annotations

from functools import cache

import numpy as np

from training.objects import Mesh

KEYPOINTS_PER_OBJECT = 8


def sample_surface(mesh: Mesh, count: int, seed: int = 0) -> np.ndarray:
    """``count`` points uniformly distributed over the mesh surface (area weighted)."""
    rng = np.random.default_rng(seed)
    tri = mesh.vertices[mesh.faces]  # (F, 3, 3)
    areas = np.linalg.norm(np.cross(tri[:, 1] - tri[:, 0], tri[:, 2] - tri[:, 0]), axis=1) / 2
    chosen = rng.choice(len(tri), size=count, p=areas / areas.sum())
    a, b = rng.random((2, count, 1))
    flip = (a + b) > 1
    a, b = np.where(flip, 1 - a, a), np.where(flip, 1 - b, b)
    t = tri[chosen]
    return t[:, 0] + a * (t[:, 1] - t[:, 0]) + b * (t[:, 2] - t[:, 0])


def farthest_points(points: np.ndarray, count: int) -> np.ndarray:
    """Greedy farthest-point sampling, starting from the point farthest from the centroid."""
    first = int(np.argmax(np.linalg.norm(points - points.mean(0), axis=1)))
    chosen = [first]
    dist = np.linalg.norm(points - points[first], axis=1)
    for _ in range(count - 1):
        nxt = int(np.argmax(dist))
        chosen.append(nxt)
        dist = np.minimum(dist, np.linalg.norm(points - points[nxt], axis=1))
    return points[chosen]


def object_keypoints(mesh: Mesh, count: int = KEYPOINTS_PER_OBJECT) -> np.ndarray:
    """``(count, 3)`` model-frame keypoints in metres."""
    return farthest_points(sample_surface(mesh, 20000), count)


@cache
def class_keypoints(class_index: int) -> np.ndarray:
    """Model-frame keypoints (metres) of one annotated object class, cached."""
    from training.objects import OBJECT_CLASSES, class_mesh

    return object_keypoints(class_mesh(OBJECT_CLASSES[class_index]))
