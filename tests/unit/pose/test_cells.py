"""Rotation cells cover SO(3), each inside its cap; branch-and-bound tightens certified bounds."""

from __future__ import annotations

import numpy as np

from service.pose import PoseOptions, instance_pose_sets
from service.pose.cells import Cell, root_cells
from service.pose.rotations import rotation_angle_deg
from tests.unit.pose.test_bounds import scene


def cell_of(quaternion: np.ndarray, cells: list[Cell]) -> Cell | None:
    """The cell holding a unit quaternion (or its negative), if any."""
    for q in (quaternion, -quaternion):
        for cell in cells:
            if q[cell.face] <= 0:
                continue
            u = np.delete(q / q[cell.face], cell.face)
            if (np.array(cell.low) <= u + 1e-12).all() and (u <= np.array(cell.high) + 1e-12).all():
                return cell
    return None


def test_cells_cover_rotations_and_lie_in_their_caps() -> None:
    rng = np.random.default_rng(5)
    cells = [grandchild for root in root_cells() for child in root.split() for grandchild in child.split()]
    assert len(cells) == 4 * 64
    for _ in range(2000):
        q = rng.normal(size=4)
        q /= np.linalg.norm(q)
        cell = cell_of(q, cells)
        assert cell is not None
        centre, cosine_squared = cell.cap()
        assert float(centre @ q) ** 2 >= cosine_squared - 1e-12


def test_splitting_tightens_the_certified_bounds_and_keeps_them_valid(camera, duck_3d, true_pose) -> None:
    centers, shapes = scene(camera, duck_3d, true_pose)
    whole = instance_pose_sets(duck_3d, centers, shapes, PoseOptions(camera, samples=60))
    split = instance_pose_sets(duck_3d, centers, shapes, PoseOptions(camera, samples=60, outer_splits=4))
    assert whole.outer.certified and split.outer.certified, (whole.outer, split.outer)
    assert split.outer.rotation_deg < whole.outer.rotation_deg
    assert split.outer.translation <= whole.outer.translation * (1 + 1e-9)
    assert "rotation cells" in split.outer.status
    estimate = split.estimate
    assert rotation_angle_deg(estimate.rotation, true_pose.rotation) <= split.outer.rotation_deg
    assert np.linalg.norm(estimate.translation - true_pose.translation) <= split.outer.translation
    assert split.inner.rotation_deg <= split.outer.rotation_deg
