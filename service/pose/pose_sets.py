"""Pose sets for the instances of one predict request (Yang & Pavone, CVPR 2023): from an object's
object-scope keypoint sets, PURSE holds the true pose with probability >= 1 - epsilon. Per instance:
an estimate inside PURSE, the inner and outer bounds on its error, and the poses asked to be checked.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass, field

import numpy as np

from service.detector.manifest import Manifest
from service.errors import InvalidInput

from .bounds import (
    InnerBound,
    SampledPoses,
    boundary_poses,
    boundary_search_available,
    inner_bound,
    sample_poses_in_set,
)
from .estimate import pnp_on_centres, refine_into_set
from .membership import Membership, Pose, membership
from .relaxation import OuterBound, outer_bound


@dataclass(frozen=True)
class PoseOptions:
    """What a request asked for: the camera, the sampling effort, the outer bound, poses to check."""

    camera: np.ndarray  # (3, 3), validated (camera.py)
    samples: int = 100
    outer: bool = True
    outer_programs: int = 150  # conic programs of the rotation search (relaxation.py)
    checks: dict[int, list[Pose]] = field(default_factory=dict)  # instance index -> poses


@dataclass(frozen=True)
class PoseCheck:
    pose: Pose
    membership: Membership


@dataclass(frozen=True)
class PoseSets:
    """One instance's pose answer; ``estimate`` None means no pose consistent with the sets was found."""

    estimate: Pose | None
    method: str  # pnp | pnp+refined-into-set | sampled | none
    violation: float | None  # the estimate's largest normalised violation (<= 1)
    inner: InnerBound | None
    inner_note: str | None
    outer: OuterBound | None
    checks: list[PoseCheck]


def check_pose_request(manifest: Manifest, objects: list[str], coverage: str, options: PoseOptions) -> None:
    """Refuse a pose request the sets cannot answer, naming the field."""
    problems = []
    if coverage != "object":
        problems.append(
            f"pose: needs coverage 'object', not {coverage!r}: only object-scope sets cover all of an "
            "object's keypoints at once, which is what carries the guarantee to the pose"
        )
    for i, name in enumerate(objects):
        if name in manifest.object_names and manifest.object(name).keypoints_3d is None:
            problems.append(
                f"instances[{i}].object: {name!r} has no keypoints_3d in the model's manifest, so it has "
                "no pose; leave it out of a pose request or add its 3D keypoints to the manifest"
            )
    problems += [
        f"pose.check: instance {i} does not exist (the request has {len(objects)} instances)"
        for i in options.checks
        if not 0 <= i < len(objects)
    ]
    if problems:
        raise InvalidInput("; ".join(problems[:5]), errors=problems)


def estimate_pose_sets(
    manifest: Manifest,
    objects: list[str],
    options: PoseOptions,
    centers: np.ndarray,
    shapes: np.ndarray,
    channel: np.ndarray,
    instance_index: np.ndarray,
) -> list[PoseSets]:
    """One PoseSets per instance, from the rows (keypoint ``channel`` of instance ``instance_index``)
    of image-pixel sets."""
    answers = []
    for i, name in enumerate(objects):
        spec = manifest.object(name)
        rows = np.flatnonzero(instance_index == i)
        position = {int(c): k for k, c in enumerate(spec.keypoints)}
        points_3d = np.asarray(spec.keypoints_3d, dtype=np.float64)[[position[int(c)] for c in channel[rows]]]
        answers.append(
            instance_pose_sets(points_3d, centers[rows], shapes[rows], options, options.checks.get(i, []))
        )
    return answers


def instance_pose_sets(
    keypoints_3d: np.ndarray,
    centers: np.ndarray,
    shapes: np.ndarray,
    options: PoseOptions,
    checks: Sequence[Pose] = (),
) -> PoseSets:
    """Estimate, bounds and checks for one instance."""
    scene = (options.camera, keypoints_3d, centers, shapes)
    checked = [PoseCheck(p, membership(p, *scene)) for p in checks]
    start = pnp_on_centres(options.camera, keypoints_3d, centers)
    if start is None:
        return PoseSets(None, "none", None, None, "fewer than 4 keypoints: no PnP", None, checked)
    estimate, method = _estimate(start, *scene)
    bounded = bool((np.linalg.eigvalsh(shapes)[:, 0] > 0).all())
    searched = boundary_search_available()
    sampled = None
    if bounded and options.samples > 0:
        sampled = sample_poses_in_set(estimate or start, *scene, options.samples)
        if estimate is None and sampled.poses:  # the least violating pose found
            worst = [membership(p, *scene).worst for p in sampled.poses]
            estimate, method = sampled.poses[int(np.argmin(worst))], "sampled"
        if estimate is not None and searched:
            boundary = boundary_poses(estimate, *scene)
            sampled = SampledPoses([*sampled.poses, *boundary], sampled.tried, len(boundary))
    inner = inner_bound(estimate, sampled) if estimate is not None and sampled is not None else None
    outer = None
    if options.outer:
        found = sampled.poses if sampled is not None else []
        programs = options.outer_programs if estimate is not None else 0
        outer = outer_bound(estimate or start, *scene, found, programs)
        if estimate is None and not outer.empty:  # bounds around a pose outside PURSE mean nothing
            outer = OuterBound(False, "no estimate in PURSE to bound around; emptiness not proven")
    violation = membership(estimate, *scene).worst if estimate is not None else None
    note = _inner_note(bounded, options.samples, searched)
    return PoseSets(estimate, method, violation, inner, note, outer, checked)


#: the inner bound without the boundary search is much smaller (docs/pose.md): said in the answer
SAMPLING_ALONE = (
    "sampling alone: the boundary search needs SciPy (pip install 'conformal-keypoint-service[pose]'),"
    " without it the inner bound is smaller"
)


def _inner_note(bounded: bool, samples: int, searched: bool) -> str | None:
    if not bounded:
        return "a keypoint set is unbounded (t = 0): PURSE does not constrain that keypoint"
    if samples == 0:
        return "pose.samples is 0: no sampling"
    return None if searched else SAMPLING_ALONE


def _estimate(start: Pose, *scene) -> tuple[Pose | None, str]:
    if membership(start, *scene).inside:
        return start, "pnp"
    refined = refine_into_set(start, *scene)
    return (refined, "pnp+refined-into-set") if refined is not None else (None, "none")
