"""The estimate lies in PURSE: PnP on the centres when it is inside, else moved inside."""

from __future__ import annotations

import numpy as np
import pytest

from service.pose import PoseOptions, instance_pose_sets, membership
from service.pose.estimate import pnp_on_centres, refine_into_set
from service.pose.rotations import rotation_angle_deg
from tests.unit.pose.conftest import balls, projections


def test_pnp_on_exact_centres_recovers_the_pose(camera, duck_3d, true_pose) -> None:
    estimate = pnp_on_centres(camera, duck_3d, projections(true_pose, camera, duck_3d))
    assert estimate is not None
    assert rotation_angle_deg(estimate.rotation, true_pose.rotation) < 1e-4
    assert np.allclose(estimate.translation, true_pose.translation, atol=1e-6)


def uneven_sets(camera, duck_3d, true_pose):
    """Large sets with large offsets and one tight set: PnP on the centres misses the tight one,
    while the true pose is inside every set (so PURSE is not empty)."""
    rng = np.random.default_rng(7)
    angles = rng.uniform(0, 2 * np.pi, 8)
    distances = np.full(8, 9.0)
    distances[2] = 0.3
    offsets = distances[:, None] * np.stack([np.cos(angles), np.sin(angles)], axis=1)
    centers = projections(true_pose, camera, duck_3d) + offsets
    radii = distances / 0.9  # the true pose sits at 0.9 of every radius
    return centers, balls(radii)


def test_a_pnp_outside_the_set_is_moved_inside(camera, duck_3d, true_pose) -> None:
    centers, shapes = uneven_sets(camera, duck_3d, true_pose)
    assert membership(true_pose, camera, duck_3d, centers, shapes).inside
    start = pnp_on_centres(camera, duck_3d, centers)
    assert not membership(start, camera, duck_3d, centers, shapes).inside  # the case under test
    refined = refine_into_set(start, camera, duck_3d, centers, shapes)
    assert refined is not None and membership(refined, camera, duck_3d, centers, shapes).inside

    answer = instance_pose_sets(duck_3d, centers, shapes, PoseOptions(camera, samples=20, outer=False))
    assert answer.method == "pnp+refined-into-set"
    assert answer.violation is not None and answer.violation <= 1.0


def test_an_estimate_inside_is_kept(camera, duck_3d, true_pose) -> None:
    centers = projections(true_pose, camera, duck_3d)
    answer = instance_pose_sets(duck_3d, centers, balls(np.full(8, 4.0)), PoseOptions(camera, 20, False))
    assert answer.method == "pnp" and answer.estimate is not None
    assert answer.violation < 1e-4


def test_inconsistent_sets_give_no_estimate(camera, duck_3d) -> None:
    """Tight sets around points no rigid pose of the duck projects to."""
    rng = np.random.default_rng(3)
    centers = rng.uniform([200, 150], [440, 330], size=(8, 2))
    answer = instance_pose_sets(duck_3d, centers, balls(np.full(8, 0.5)), PoseOptions(camera, 50, True))
    assert answer.estimate is None and answer.method == "none"
    assert answer.inner is None
    outer = answer.outer
    assert outer is not None and outer.rotation_deg is None and outer.translation is None
    # only a proof of emptiness may be certified, never bounds around nothing
    assert outer.certified == outer.empty


def test_too_few_keypoints_give_no_estimate(camera, duck_3d, true_pose) -> None:
    centers = projections(true_pose, camera, duck_3d)[:3]
    answer = instance_pose_sets(duck_3d[:3], centers, balls(np.full(3, 4.0)), PoseOptions(camera))
    assert answer.estimate is None and answer.method == "none"


@pytest.mark.parametrize("scale", [1e-300, 1e-12, 1e12, 1e300])
def test_extreme_cameras_give_an_answer_not_an_error(duck_3d, true_pose, scale: float) -> None:
    """A valid but absurd K never raises: at worst no estimate and no certificate."""
    camera = np.array([[572.0 * scale, 0.0, 320.0], [0.0, 572.0 * scale, 240.0], [0.0, 0.0, 1.0]])
    centers = np.random.default_rng(1).uniform(0, 640, (8, 2))
    answer = instance_pose_sets(duck_3d, centers, balls(np.full(8, 5.0)), PoseOptions(camera, samples=10))
    assert answer.method in {"pnp", "pnp+refined-into-set", "sampled", "none"}
    if answer.estimate is not None:
        assert membership(answer.estimate, camera, duck_3d, centers, balls(np.full(8, 5.0))).inside
