"""PURSE membership is exact: in front of the camera and inside every ball or ellipse."""

from __future__ import annotations

import numpy as np

from service.pose import Pose, membership, pose_in_set
from service.pose.membership import poses_inside
from service.pose.rotations import from_rotation_vector
from tests.unit.pose.conftest import balls, projections


def test_the_pose_that_made_the_centres_is_inside(camera, duck_3d, true_pose) -> None:
    centers = projections(true_pose, camera, duck_3d)
    check = membership(true_pose, camera, duck_3d, centers, balls(np.full(8, 2.0)))
    assert check.inside and check.in_front.all()
    assert np.allclose(check.violations, 0.0, atol=1e-9)


def test_membership_is_exact_at_the_boundary(camera, duck_3d, true_pose) -> None:
    """A keypoint offset by d from its centre is in a ball of radius r exactly when d <= r."""
    offset = np.zeros((8, 2))
    offset[3] = (3.0, 4.0)  # 5 px away
    centers = projections(true_pose, camera, duck_3d) + offset
    violations = membership(true_pose, camera, duck_3d, centers, balls(np.full(8, 10.0))).violations
    assert np.isclose(violations[3], 0.5)
    for radius, inside in [(5.0 * (1 + 1e-9), True), (5.0 * (1 - 1e-9), False)]:
        shapes = balls(np.full(8, radius))
        found = pose_in_set(true_pose.rotation, true_pose.translation, camera, duck_3d, centers, shapes)
        assert found is inside


def test_ellipses_use_their_shape_matrix(camera, duck_3d, true_pose) -> None:
    offset = np.zeros((8, 2))
    offset[0] = (6.0, 0.0)
    centers = projections(true_pose, camera, duck_3d) + offset
    wide = np.tile(np.diag([1 / 8.0**2, 1 / 2.0**2]), (8, 1, 1))  # semi-axes 8 along x, 2 along y
    tall = np.tile(np.diag([1 / 2.0**2, 1 / 8.0**2]), (8, 1, 1))
    assert membership(true_pose, camera, duck_3d, centers, wide).inside
    check = membership(true_pose, camera, duck_3d, centers, tall)
    assert not check.inside and np.isclose(check.violations[0], 3.0)


def test_perturbed_poses_leave_the_set(camera, duck_3d, true_pose) -> None:
    centers = projections(true_pose, camera, duck_3d)
    shapes = balls(np.full(8, 3.0))
    moved = Pose(true_pose.rotation, true_pose.translation + np.array([20.0, 0.0, 0.0]))
    turned = Pose(from_rotation_vector(np.array([0.0, 0.0, 0.3])) @ true_pose.rotation, true_pose.translation)
    for pose in (moved, turned):
        assert not membership(pose, camera, duck_3d, centers, shapes).inside


def test_a_keypoint_behind_the_camera_is_outside_even_in_an_unbounded_set(camera, duck_3d, true_pose) -> None:
    centers = projections(true_pose, camera, duck_3d)
    unbounded = np.zeros((8, 2, 2))
    assert membership(true_pose, camera, duck_3d, centers, unbounded).inside
    behind = Pose(true_pose.rotation, -true_pose.translation)
    check = membership(behind, camera, duck_3d, centers, unbounded)
    assert not check.inside and not check.in_front.any() and np.isinf(check.violations).all()


def test_a_batch_answers_as_each_pose_alone_even_at_the_edge(camera, duck_3d, true_pose) -> None:
    """Poses on a segment out of PURSE, across its edge to the last bit (30 representable steps on
    each side, where a batch's rounding differs from one pose's: this scene is one where it decided
    otherwise before), and behind the camera: ``poses_inside`` gives ``membership``'s answers."""
    rng = np.random.default_rng(15)
    centers = projections(true_pose, camera, duck_3d) + rng.normal(0, 1.0, (8, 2))
    shapes = balls(np.full(8, 4.0))
    axis = rng.normal(size=3) * 0.05

    def pose_at(fraction: float) -> Pose:
        return Pose(
            from_rotation_vector(fraction * axis) @ true_pose.rotation, true_pose.translation + 30 * fraction
        )

    def inside(fraction: float) -> bool:
        return membership(pose_at(fraction), camera, duck_3d, centers, shapes).inside

    low, high = 0.0, 1.0
    assert inside(low) and not inside(high)
    for _ in range(60):
        middle = (low + high) / 2
        low, high = (middle, high) if inside(middle) else (low, middle)
    fractions = [*np.linspace(0, 1, 20), low, high]
    for _ in range(30):
        fractions += [np.nextafter(fractions[-2], -1.0), np.nextafter(fractions[-1], 2.0)]
    poses = [pose_at(f) for f in fractions] + [Pose(true_pose.rotation, -true_pose.translation)]
    alone = [membership(p, camera, duck_3d, centers, shapes).inside for p in poses]
    rotations, translations = np.array([p.rotation for p in poses]), np.array([p.translation for p in poses])
    assert poses_inside(rotations, translations, camera, duck_3d, centers, shapes).tolist() == alone
    assert alone.count(True) > 30 and alone.count(False) > 30
