"""Synthetic scenes for the pose unit tests: the manifest's duck seen by the samples' camera."""

from __future__ import annotations

import json

import numpy as np
import pytest

from service.infra.settings import Settings
from service.pose import Pose
from service.pose.membership import camera_points, project
from service.pose.rotations import from_rotation_vector


@pytest.fixture(scope="session")
def camera() -> np.ndarray:
    return np.array([[572.0, 0.0, 320.0], [0.0, 572.0, 240.0], [0.0, 0.0, 1.0]])


@pytest.fixture(scope="session")
def duck_3d() -> np.ndarray:
    manifest = json.loads((Settings().model.directory / "manifest.json").read_text())
    return np.array(next(o for o in manifest["objects"] if o["name"] == "duck")["keypoints_3d"])


@pytest.fixture(scope="session")
def true_pose() -> Pose:
    return Pose(from_rotation_vector(np.array([0.4, -1.2, 0.7])), np.array([-60.0, 10.0, 850.0]))


def balls(radii: np.ndarray) -> np.ndarray:
    """Shape matrices I / r^2."""
    return np.eye(2)[None] / np.asarray(radii, dtype=np.float64)[:, None, None] ** 2


def projections(pose: Pose, camera: np.ndarray, keypoints_3d: np.ndarray) -> np.ndarray:
    return project(camera_points(pose, keypoints_3d), camera)
