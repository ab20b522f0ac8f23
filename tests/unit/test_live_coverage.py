"""Live coverage's fold: a look votes once it is complete, with the share covered of all its
labelled frames; a stream's next look completes it; streams keep their looks apart."""

from __future__ import annotations

import json

from calibration_store import LabelVerdicts
from service.feedback.live_coverage import CoverageFold, GroupCoverage

UNITS = 4


def label(stream: str, look: str, covered: int, units: int = UNITS) -> LabelVerdicts:
    """A frame's verdicts: ``units`` keypoints of one calibration guarantee, ``covered`` of them."""
    runs = [[0, units]]
    shape = {
        "version": 1,
        "guarantee": "exchangeable",
        "query": ["cov", "keypoint", 0.1, None],
        "floors": [[[600, 60, 0.1, None]]],  # per floor: the guarantees of its rows
        "groups": [["version", "all", runs], ["stream", stream, runs]],
    }
    return LabelVerdicts(json.dumps(shape), {"look": look, "covered": [covered, covered]})


def group(fold: CoverageFold, level: str, name: str) -> GroupCoverage:
    return next(g for g in fold.report() if g.level == level and g.name == name)


def test_a_look_votes_the_share_of_all_its_labelled_frames_once_the_next_look_comes() -> None:
    fold = CoverageFold(0.05, 100)
    for covered in (3, 1):  # two frames of look a1: 4 of 8 covered
        fold.add(label("cam-a", "a1", covered))
    opened = group(fold, "version", "all")
    assert (opened.labelled, opened.covered, opened.looks) == (8, 4, 0)  # counted raw, not voted yet
    fold.add(label("cam-a", "a2", 4))  # the next look of cam-a: a1 is complete
    voted = group(fold, "version", "all")
    assert (voted.looks, voted.look_mean) == (1, 0.5)
    fold.add(label("cam-a", "a1", 0))  # a late frame of a1: raw counts only, its vote is cast
    late = group(fold, "version", "all")
    assert (late.labelled, late.covered, late.looks, late.look_mean) == (16, 8, 1, 0.5)


def test_interleaved_streams_complete_only_their_own_looks() -> None:
    fold = CoverageFold(0.05, 100)
    for stream, look, covered in (
        ("cam-a", "a1", 4),
        ("cam-b", "b1", 0),
        ("cam-a", "a1", 2),
        ("cam-b", "b2", 4),
    ):
        fold.add(label(stream, look, covered))
    assert group(fold, "stream", "cam-a").looks == 0  # a1 open: cam-b's looks do not complete it
    assert (group(fold, "stream", "cam-b").looks, group(fold, "stream", "cam-b").look_mean) == (1, 0.0)
    fold.add(label("cam-a", "a2", 4))
    cam_a = group(fold, "stream", "cam-a")
    assert (cam_a.looks, cam_a.look_mean) == (1, 0.75)
    assert group(fold, "version", "all").looks == 2


def test_a_looks_frames_of_other_shapes_pool_into_the_groups_they_share() -> None:
    fold = CoverageFold(0.05, 100)
    fold.add(label("cam-a", "a1", 3))  # 3 of 4
    fold.add(label("cam-a", "a1", 2, units=2))  # another shape (2 keypoints labelled): 2 of 2
    fold.add(label("cam-a", "a2", 0))
    voted = group(fold, "version", "all")
    assert (voted.looks, voted.look_mean, voted.labelled) == (1, 5 / 6, 10)
