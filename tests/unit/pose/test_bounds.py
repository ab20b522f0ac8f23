"""Bounds on the pose error: sampled poses are in PURSE; the certified outer bound dominates them
and the error of any pose in PURSE (the true one included)."""

from __future__ import annotations

import sys

import numpy as np
import pytest

from service.pose import Pose, PoseOptions, instance_pose_sets, membership
from service.pose.bounds import (
    SampledPoses,
    boundary_poses,
    inner_bound,
    sample_points_in_sets,
    sample_poses_in_set,
)
from service.pose.membership import set_violations
from service.pose.pose_sets import SAMPLING_ALONE
from service.pose.relaxation import outer_bound
from service.pose.rotations import from_rotation_vector, rotation_angle_deg
from tests.unit.pose.conftest import balls, projections


def ellipses(count: int, rng: np.random.Generator) -> np.ndarray:
    shapes = []
    for _ in range(count):
        a, b, angle = rng.uniform(2, 6), rng.uniform(6, 12), rng.uniform(0, np.pi)
        rotation = np.array([[np.cos(angle), -np.sin(angle)], [np.sin(angle), np.cos(angle)]])
        shapes.append(rotation @ np.diag([1 / a**2, 1 / b**2]) @ rotation.T)
    return np.array(shapes)


def test_points_are_drawn_inside_their_sets() -> None:
    rng = np.random.default_rng(0)
    shapes = ellipses(8, rng)
    centers = rng.uniform(0, 500, (8, 2))
    for _ in range(200):
        assert (set_violations(sample_points_in_sets(centers, shapes, rng)[0], centers, shapes) <= 1).all()


def scene(camera, duck_3d, true_pose, rng: np.random.Generator | None = None):
    rng = rng or np.random.default_rng(11)
    shapes = ellipses(8, rng)
    # centres moved off the truth by half of each set's size, in random directions
    angle = rng.uniform(0, 2 * np.pi, 8)
    unit = np.stack([np.cos(angle), np.sin(angle)], axis=1)
    scale = 0.5 / np.sqrt(np.einsum("ni,nij,nj->n", unit, shapes, unit))
    centers = projections(true_pose, camera, duck_3d) + unit * scale[:, None]
    return centers, shapes


def test_sampled_poses_are_in_purse(camera, duck_3d, true_pose) -> None:
    centers, shapes = scene(camera, duck_3d, true_pose)
    sampled = sample_poses_in_set(true_pose, camera, duck_3d, centers, shapes, 60)
    assert len(sampled.poses) >= 5
    assert all(membership(p, camera, duck_3d, centers, shapes).inside for p in sampled.poses)


def test_the_boundary_search_finds_poses_in_purse_farther_than_sampling(camera, duck_3d, true_pose) -> None:
    centers, shapes = scene(camera, duck_3d, true_pose)
    sampled = sample_poses_in_set(true_pose, camera, duck_3d, centers, shapes, 100)
    boundary = boundary_poses(true_pose, camera, duck_3d, centers, shapes)
    assert len(boundary) == 6  # along and against the line of sight, four turns across it
    assert all(membership(p, camera, duck_3d, centers, shapes).inside for p in boundary)
    assert max(membership(p, camera, duck_3d, centers, shapes).worst for p in boundary) > 0.999  # on the edge
    far, near = (inner_bound(true_pose, found) for found in (SampledPoses(boundary, 0), sampled))
    assert far.translation > 1.2 * near.translation and far.rotation_deg > 1.2 * near.rotation_deg


def test_the_certified_outer_bound_dominates_the_inner_bound_and_the_true_error(
    camera, duck_3d, true_pose
) -> None:
    centers, shapes = scene(camera, duck_3d, true_pose)
    assert membership(true_pose, camera, duck_3d, centers, shapes).inside
    answer = instance_pose_sets(duck_3d, centers, shapes, PoseOptions(camera, samples=100))
    estimate, inner, outer = answer.estimate, answer.inner, answer.outer
    assert estimate is not None and inner is not None and outer is not None
    assert outer.certified, outer.status
    assert inner.poses_found > 0 and inner.boundary_poses == 6
    assert answer.inner_note is None  # sampling and the boundary search made the inner bound
    assert inner.rotation_deg <= outer.rotation_deg
    assert inner.translation <= outer.translation
    assert rotation_angle_deg(estimate.rotation, true_pose.rotation) <= outer.rotation_deg
    assert np.linalg.norm(estimate.translation - true_pose.translation) <= outer.translation


def test_without_scipy_the_answer_says_its_inner_bound_is_sampling_alone(
    camera, duck_3d, true_pose, monkeypatch: pytest.MonkeyPatch
) -> None:
    """The default install has no SciPy: the import fails as it does there, and the note says so."""
    monkeypatch.setitem(sys.modules, "scipy.optimize", None)  # `import scipy.optimize` raises ImportError
    centers, shapes = scene(camera, duck_3d, true_pose)
    answer = instance_pose_sets(duck_3d, centers, shapes, PoseOptions(camera, samples=100, outer=False))
    assert answer.inner is not None and answer.inner.boundary_poses == 0
    assert answer.inner_note == SAMPLING_ALONE and "SciPy" in SAMPLING_ALONE


def test_a_bound_below_a_sampled_pose_is_not_certified(camera, duck_3d, true_pose) -> None:
    """The domination check bites: a 'sampled pose' far outside the relaxation voids the certificate."""
    centers, shapes = scene(camera, duck_3d, true_pose)
    far = Pose(from_rotation_vector(np.array([3.0, 0.0, 0.0])), true_pose.translation * 5)
    assert not outer_bound(true_pose, camera, duck_3d, centers, shapes, [far]).certified


def test_unbounded_sets_have_no_sampled_bound(camera, duck_3d, true_pose) -> None:
    centers = projections(true_pose, camera, duck_3d)
    shapes = balls(np.full(8, 4.0))
    shapes[5] = 0.0  # t = 0 for this keypoint
    answer = instance_pose_sets(duck_3d, centers, shapes, PoseOptions(camera, samples=50))
    assert answer.estimate is not None and answer.inner is None
    assert "unbounded" in answer.inner_note
