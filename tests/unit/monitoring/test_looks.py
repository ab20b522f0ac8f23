"""The sequential drift alarm: looks, flatness z-scores, the e-CUSUM, and the monitor that uses them.

The looks and the alarm on crafted frames; the z-scores on the bundled calibration split in two
(one half the reference, the other half live: exchangeable, so the z must look standard normal).
"""

from __future__ import annotations

from dataclasses import replace

import numpy as np
import pytest

from calibration_store import ObjectScores, ScoreTable
from service.calibration.bundle import BUNDLE_FILENAME, load_bundle
from service.conformal import ball_shapes
from service.conformal.features import HEATMAP_FEATURES
from service.infra.settings import DEFAULT_MODEL_DIR
from service.monitoring.drift_monitor import DriftMonitor
from service.monitoring.looks import (
    WITHIN_FRAME_CORRELATION,
    FlatnessReference,
    Frame,
    InstanceFeatures,
    LookTracker,
    SequentialAlarm,
)
from tests.unit.monitoring.test_drift_monitor import MANIFEST, SETTINGS, _monitor, _statistics, _table

SEQUENTIAL = replace(SETTINGS, test="sequential")


def _frame(*boxes: tuple[str, float, float]) -> Frame:
    return Frame(tuple(name for name, _, _ in boxes), np.array([[x, y, 80.0, 60.0] for _, x, y in boxes]))


def test_a_scene_is_one_look_however_long_and_a_cut_starts_another() -> None:
    looks = LookTracker()
    scene = [_frame(("duck", 100 + 2 * k, 50), ("mug", 300 - k, 80)) for k in range(300)]
    assert [looks.is_new_look(f) for f in scene].count(True) == 1  # a slow pan: one look
    assert looks.is_new_look(_frame(("lego", 20, 300)))  # a cut: other objects
    assert looks.is_new_look(_frame(("duck", 400, 300)))  # the same object, elsewhere
    assert not looks.is_new_look(scene[0])  # an image seen before, sent again
    four = _frame(("duck", 0, 0), ("mug", 200, 0), ("lego", 400, 0), ("bunny", 0, 300))
    assert looks.is_new_look(four)
    by_chance = _frame(("duck", 5, 5), ("mug", 500, 400), ("blob", 200, 200), ("teddy", 300, 300))
    assert looks.is_new_look(by_chance)  # a cut that puts one of four objects where it was
    assert not looks.is_new_look(_frame(("duck", 8, 8), ("mug", 504, 402), ("blob", 203, 200)))  # teddy left
    assert looks.is_new_look(None) and looks.is_new_look(None)  # without boxes every frame counts


def test_cameras_calling_at_once_each_keep_their_scene() -> None:
    looks = LookTracker()
    cameras = [[_frame(("duck", 100 * c + k, 50 * c)) for k in range(50)] for c in range(3)]
    interleaved = [frame for frames in zip(*cameras, strict=True) for frame in frames]
    assert [looks.is_new_look(f) for f in interleaved].count(True) == 3


def test_the_alarm_is_rare_on_independent_quiet_looks_and_fast_on_a_shift() -> None:
    rng = np.random.default_rng(3)
    level, looks, instances = 0.01, 20_000, 4
    shared = np.sqrt(WITHIN_FRAME_CORRELATION)  # instances of one image correlated as much as allowed

    def look(shift: float) -> list[float]:
        common = rng.normal()
        return (shift + shared * common + np.sqrt(1 - shared**2) * rng.normal(size=instances)).tolist()

    alarm, false_alarms = SequentialAlarm(level), 0
    for _ in range(looks):
        alarm.observe(look(0.0))
        if alarm.alarm:
            false_alarms, alarm = false_alarms + 1, SequentialAlarm(level)
    assert false_alarms <= looks * level  # at least 1/level looks between false alarms, on average

    delays = []
    for _ in range(20):
        alarm = SequentialAlarm(level)
        while not alarm.alarm:
            alarm.observe(look(0.5))
        delays.append(alarm.looks)
    assert np.median(delays) < 40, delays


def _half(table: ScoreTable, part: int) -> ScoreTable:
    blocks = []
    for block in table.objects:
        rows = np.arange(block.n_instances) % 2 == part
        blocks.append(
            ObjectScores(
                object_name=block.object_name,
                keypoint_ids=block.keypoint_ids,
                instance_refs=tuple(r for r, keep in zip(block.instance_refs, rows, strict=True) if keep),
                scores={kind: scores[rows] for kind, scores in block.scores.items()},
                features={name: np.asarray(values)[rows] for name, values in block.features.items()},
            )
        )
    return ScoreTable(tuple(blocks))


@pytest.mark.parametrize("computed", [HEATMAP_FEATURES, ("gamma", "anisotropy"), ("peak_probability",)])
def test_live_instances_like_the_calibration_get_standard_normal_z(computed: tuple[str, ...]) -> None:
    _, table = load_bundle(DEFAULT_MODEL_DIR / BUNDLE_FILENAME)
    reference = FlatnessReference(_half(table, 0), MANIFEST.num_keypoints)
    z = []
    for block in _half(table, 1).objects:
        matrix = np.stack(
            [np.asarray(block.features[name], dtype=float) for name in HEATMAP_FEATURES], axis=2
        )
        for name in set(HEATMAP_FEATURES) - set(computed):
            matrix[:, :, HEATMAP_FEATURES.index(name)] = np.nan
        for row in matrix:
            z.append(
                reference.instance_z(InstanceFeatures(block.object_name, np.asarray(block.keypoint_ids), row))
            )
    z = np.array(z)
    assert len(z) > 1000 and abs(z.mean()) < 0.1 and 0.9 < z.std() < 1.1


def _frames(
    monitor: DriftMonitor,
    rng: np.random.Generator,
    frames: list[Frame],
    blur: float = 1.0,
    same: bool = False,
) -> None:
    fixed = None
    for frame in frames:
        channels = np.concatenate([MANIFEST.object(name).keypoints for name in frame.objects])
        statistics = fixed if same and fixed is not None else _statistics(rng, channels.size, blur)
        fixed = statistics
        monitor.record(channels, statistics, "cov", ball_shapes(np.full(channels.size, 10.0)), frame)


def test_a_static_scene_stays_quiet_and_counts_one_look() -> None:
    rng = np.random.default_rng(4)
    monitor = _monitor(_table(rng), SEQUENTIAL)
    odd = [_frame(("duck", 100, 50), ("mug", 300, 80))] * 300
    _frames(monitor, rng, odd, blur=1.6, same=True)  # an unusual scene, filmed for 300 frames
    report = monitor.report()
    assert report.sequential is not None and report.sequential.frames == 300
    assert report.sequential.looks == 1 and not report.alarm
    assert all(t.live_n == 1 for k in report.keypoints for t in k.features.values() if t.live_n)


def test_a_shifted_stream_of_new_scenes_alarms() -> None:
    rng = np.random.default_rng(5)
    monitor = _monitor(_table(rng), SEQUENTIAL)
    scenes = [_frame(("duck", 10 + k, 50), ("mug", 300, 80 + k)) for k in range(0, 6000, 100)]
    _frames(monitor, rng, scenes[:30])
    quiet = monitor.report()
    assert quiet.sequential.looks == 30 and not quiet.alarm
    _frames(monitor, rng, scenes[30:], blur=1.6)
    shifted = monitor.report()
    assert shifted.alarm and shifted.sequential.evidence >= shifted.sequential.threshold
    assert any(t.alarm for k in shifted.keypoints for t in k.features.values())  # where it moved
