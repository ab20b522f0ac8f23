"""Rotation wedges cover SO(3) (or the rotations near an estimate); the search over them tightens
certified bounds and keeps them valid."""

from __future__ import annotations

import itertools
import math

import numpy as np

from service.pose import Pose, PoseOptions, instance_pose_sets, membership
from service.pose.cells import SIDES, Wedge
from service.pose.relaxation import ROTATION_TOLERANCE, TRANSLATION_TOLERANCE
from service.pose.rotations import from_rotation_vector, left_product, rotation_angle_deg, to_quaternion
from tests.unit.pose.test_bounds import scene


def cell_of(quaternion: np.ndarray, cells: list[Wedge]) -> Wedge | None:
    """The wedge around the identity holding a unit quaternion (or its negative), if any."""
    for q in (quaternion, -quaternion):
        for cell in cells:
            if q[cell.face] <= 0:
                continue
            u = np.delete(q / q[cell.face], cell.face)
            if (np.array(cell.low) <= u + 1e-12).all() and (u <= np.array(cell.high) + 1e-12).all():
                return cell
    return None


def sides(wedge: Wedge, estimate: np.ndarray) -> list[tuple[np.ndarray, np.ndarray]]:
    """Per side, (a, b) in absolute quaternion coordinates: a^T q q^T b <= 0 on the wedge."""
    forms = wedge.forms(left_product(to_quaternion(estimate)))
    return list(zip(-forms[SIDES[0]], forms[SIDES[1]], strict=True))


def test_split_faces_cover_rotations() -> None:
    rng = np.random.default_rng(5)
    cells = Wedge.around(math.pi)
    for _ in range(2):
        cells = [child for cell in cells for child in cell.split(math.pi)]
    assert len(cells) == 4 * 64
    for _ in range(2000):
        q = rng.normal(size=4)
        q /= np.linalg.norm(q)
        assert cell_of(q, cells) is not None


def test_wedges_cover_the_rotations_near_an_estimate_and_their_sides_cut_them_out() -> None:
    """Every rotation within the radius lies in a wedge (three splits deep), and a wedge's rotations,
    and only they, satisfy its three side constraints; each lies between its nearest and farthest
    angles."""
    rng = np.random.default_rng(6)
    estimate = from_rotation_vector(np.array([0.3, -1.0, 2.0]))
    radius = 1.2
    wedges = Wedge.around(radius)
    for _ in range(3):
        wedges = [child for wedge in wedges for child in wedge.split(radius)]
    assert 64 < len(wedges) < 512  # the corners outside the ball are left out
    anchor = left_product(to_quaternion(estimate))
    for _ in range(2000):
        w = rng.normal(size=3)
        w *= rng.uniform(0, radius) / np.linalg.norm(w)
        rotation = estimate @ from_rotation_vector(w)
        q = to_quaternion(rotation)
        relative = anchor.T @ q  # the quaternion of R_hat^T R
        inside = [
            wedge
            for wedge in wedges
            if all(float(a @ q) * float(b @ q) <= 1e-12 for a, b in sides(wedge, estimate))
        ]
        assert inside, w
        for wedge in inside:
            gibbs = relative[1:] / relative[0]
            assert (np.array(wedge.low) - 1e-9 <= gibbs).all() and (
                gibbs <= np.array(wedge.high) + 1e-9
            ).all()
            angle = np.radians(rotation_angle_deg(estimate, rotation))
            assert wedge.nearest_angle() - 1e-12 <= angle <= wedge.farthest_angle() + 1e-12


def test_the_four_faces_cover_every_rotation() -> None:
    rng = np.random.default_rng(7)
    estimate = from_rotation_vector(np.array([-2.0, 0.5, 0.1]))
    faces = Wedge.around(np.radians(170.0))
    assert len(faces) == 4
    for _ in range(500):
        q = rng.normal(size=4)
        q /= np.linalg.norm(q)
        assert any(
            all(float(a @ q) * float(b @ q) <= 1e-12 for a, b in sides(face, estimate)) for face in faces
        )


def test_the_quaternion_is_the_rotations() -> None:
    from service.pose.rotations import QUATERNION_BASIS

    rotation = from_rotation_vector(np.array([0.4, -2.5, 1.1]))
    q = to_quaternion(rotation)
    assert np.allclose(np.einsum("a,jkab,b->jk", q, QUATERNION_BASIS, q), rotation)


def test_the_search_tightens_the_certified_bounds_and_keeps_them_valid(camera, duck_3d, true_pose) -> None:
    centers, shapes = scene(camera, duck_3d, true_pose)
    whole = instance_pose_sets(duck_3d, centers, shapes, PoseOptions(camera, samples=60, outer_programs=0))
    assert whole.outer.certified and "whole rotation space" in whole.outer.status, whole.outer
    for options in ({"outer_programs": 60}, {}):
        split = instance_pose_sets(duck_3d, centers, shapes, PoseOptions(camera, samples=60, **options))
        assert split.outer.certified, (options, split.outer)
        assert split.outer.rotation_deg < whole.outer.rotation_deg
        assert split.outer.translation <= whole.outer.translation * (1 + 1e-9)
        assert "rotation cells" in split.outer.status
        estimate = split.estimate
        assert rotation_angle_deg(estimate.rotation, true_pose.rotation) <= split.outer.rotation_deg
        assert np.linalg.norm(estimate.translation - true_pose.translation) <= split.outer.translation
        assert split.inner.rotation_deg <= split.outer.rotation_deg
        assert split.inner.translation <= split.outer.translation


def test_more_programs_never_loosen_the_search(camera, duck_3d, true_pose) -> None:
    """The search only ever lowers a cube's bounds, splits cubes or drops empty ones: a larger budget
    continues the same steps, so its bounds are at most the smaller budget's."""
    centers, shapes = scene(camera, duck_3d, true_pose)
    answers = [
        instance_pose_sets(duck_3d, centers, shapes, PoseOptions(camera, samples=0, outer_programs=n))
        for n in (0, 10, 40, 120)
    ]
    for looser, tighter in itertools.pairwise(answer.outer for answer in answers):
        assert tighter.certified, tighter
        assert tighter.rotation_deg <= looser.rotation_deg and tighter.translation <= looser.translation
    assert answers[-1].outer.rotation_deg < 0.5 * answers[0].outer.rotation_deg


def test_the_search_stops_within_its_stated_tolerance_and_its_bounds_hold(camera, duck_3d) -> None:
    """On scenes whose true pose is in PURSE: the certified bounds contain the true pose's error and
    every pose found; a search that stopped before its budget has its bounds within
    ROTATION_TOLERANCE and TRANSLATION_TOLERANCE of the poses found."""
    rng = np.random.default_rng(21)
    stopped = 0
    for _ in range(4):
        truth = Pose(from_rotation_vector(rng.normal(size=3)), np.array([*rng.uniform(-80, 80, 2), 800.0]))
        centers, shapes = scene(camera, duck_3d, truth, rng)
        assert membership(truth, camera, duck_3d, centers, shapes).inside
        answer = instance_pose_sets(
            duck_3d, centers, shapes, PoseOptions(camera, samples=50, outer_programs=400)
        )
        estimate, inner, outer = answer.estimate, answer.inner, answer.outer
        assert outer.certified, outer.status
        assert rotation_angle_deg(estimate.rotation, truth.rotation) <= outer.rotation_deg
        assert np.linalg.norm(estimate.translation - truth.translation) <= outer.translation
        assert inner.rotation_deg <= outer.rotation_deg and inner.translation <= outer.translation
        if int(outer.status.split("(")[1].split(" ")[0]) < 400:
            stopped += 1
            assert outer.rotation_deg <= ROTATION_TOLERANCE * inner.rotation_deg * (1 + 1e-9)
            assert outer.translation <= TRANSLATION_TOLERANCE * inner.translation * (1 + 1e-9)
    assert stopped >= 3
