"""A drift alarm that stays right on camera streams: one vote per independent look, summed by a
sequential test whose false alarms are bounded. A frame is a new look unless half its instances
continue one of the last ``INTERLEAVED_STREAMS`` frames' (same object, IoU >= ``CONTINUATION_IOU``)
or it repeats a recent look. Per look, its instances' z_i ~ N(0, 1) (normal scores of their features'
ranks among the calibration's, ranked among the calibration instances' own) give
``Z = sum z_i / sqrt(m (1 + (m - 1) rho))`` (variance <= 1 while instances of one image correlate at
most ``rho``); e-values ``exp(+-lambda Z - lambda^2 / 2)`` feed two CUSUMs ``M = e * max(M, 1)``,
alarming at ``2 / alarm_level``: >= ``1 / alarm_level`` quiet looks between false alarms on average
(Lorden's bound for e-detectors: Shin, Ramdas & Rinaldo, 2023).
"""

from __future__ import annotations

import hashlib
import math
from collections import OrderedDict, deque
from dataclasses import dataclass
from statistics import NormalDist

import numpy as np

from calibration_store import ScoreTable
from service.conformal.features import HEATMAP_FEATURES

#: box overlap at which an instance continues one of a previous frame (same object)
CONTINUATION_IOU = 0.3
#: bound on the correlation of the z of two instances of one image (measured 0.09-0.15)
WITHIN_FRAME_CORRELATION = 0.25
#: e-value step: best against a shift of about this much in a look's Z
LAMBDA = 0.5
#: recent frames a frame may continue: cameras whose requests interleave in one process
INTERLEAVED_STREAMS = 8
#: recent looks whose objects and boxes a new frame must differ from
REMEMBERED_LOOKS = 10_000
#: the key of a look whose frame has no boxes
NO_KEY = 0
#: sign of each feature in the flatness score: a flatter heatmap has a lower p*, larger gamma
SIGNS = {"peak_probability": -1.0, "gamma": 1.0, "anisotropy": 1.0}
_NORMAL = NormalDist()


@dataclass(frozen=True)
class Frame:
    """What a request says about its image: its instances' objects and boxes (x, y, w, h)."""

    objects: tuple[str, ...]
    boxes: np.ndarray  # (N, 4)


@dataclass(frozen=True)
class InstanceFeatures:
    """One instance of a look: its object, keypoint channels and features (NaN: not computed)."""

    object: str
    channels: np.ndarray  # (k,)
    features: np.ndarray  # (k, len(HEATMAP_FEATURES))


@dataclass(frozen=True)
class SequentialState:
    looks: int  # independent looks tested against the reference
    frames: int  # frames recorded
    evidence: float  # max of the two CUSUMs (1: none)
    threshold: float  # 2 / alarm_level
    alarm: bool


class LookTracker:
    """Tells a new look from a frame that continues (or repeats) one."""

    def __init__(self) -> None:
        self._recent: deque[Frame] = deque(maxlen=INTERLEAVED_STREAMS)
        self._seen: OrderedDict[int, None] = OrderedDict()  # oldest first

    def is_new_look(self, frame: Frame | None) -> bool:
        """None (no boxes known): every frame is a look."""
        return self.new_look_key(frame) is not None

    def new_look_key(self, frame: Frame | None) -> int | None:
        """The key of the look ``frame`` starts, None when it continues or repeats one."""
        if frame is None:
            return NO_KEY
        continued = any(continues(previous, frame) for previous in self._recent)
        self._recent.append(frame)
        key = None if continued else look_key(frame)
        if key is None or key in self._seen:
            return None
        self._remember_key(key)
        return key

    def remember(self, frames: list[Frame], keys: list[int]) -> None:
        """Continue where another tracker stopped: its last frames and its looks' keys."""
        self._recent.extend(frames[-INTERLEAVED_STREAMS:])
        for key in keys:
            if key != NO_KEY and key not in self._seen:
                self._remember_key(key)

    def _remember_key(self, key: int) -> None:
        self._seen[key] = None
        if len(self._seen) > REMEMBERED_LOOKS:
            self._seen.popitem(last=False)


def look_key(frame: Frame) -> int:
    """The frame's objects and boxes (to 0.1 px) as a 64-bit number, the same in every process."""
    text = repr((frame.objects, np.round(frame.boxes, 1).tolist())).encode()
    return int.from_bytes(hashlib.blake2b(text, digest_size=8).digest(), "little", signed=True)


def continues(previous: Frame, frame: Frame) -> bool:
    """At least half of the frame's instances continue one of the previous frame's."""
    before = list(zip(previous.objects, previous.boxes.tolist(), strict=True))  # floats: 10x faster
    matched = sum(
        any(name == other_name and _iou(box, other) >= CONTINUATION_IOU for other_name, other in before)
        for name, box in zip(frame.objects, frame.boxes.tolist(), strict=True)
    )
    return matched > 0 and 2 * matched >= len(frame.objects)


def _iou(a: list[float], b: list[float]) -> float:
    width = min(a[0] + a[2], b[0] + b[2]) - max(a[0], b[0])
    height = min(a[1] + a[3], b[1] + b[3]) - max(a[1], b[1])
    inter = max(width, 0.0) * max(height, 0.0)
    union = a[2] * a[3] + b[2] * b[3] - inter
    return inter / union if union > 0 else 0.0


def sorted_features(table: ScoreTable, channels: int) -> list[list[np.ndarray | None]]:
    """[feature][channel]: the calibration's finite values, sorted (None: channel not in the version)."""
    values: list[list[np.ndarray | None]] = [[None] * channels for _ in HEATMAP_FEATURES]
    for block in table.objects:
        for position, name in enumerate(HEATMAP_FEATURES):
            matrix = np.asarray(block.features[name], dtype=np.float64)
            for column, channel in enumerate(block.keypoint_ids):
                values[position][int(channel)] = np.sort(matrix[np.isfinite(matrix[:, column]), column])
    return values


def _ranks(reference: np.ndarray, values: np.ndarray | float, leave_one_out: bool = False) -> np.ndarray:
    """Mid-ranks in (0, 1) among ``reference``; leave_one_out: values of the reference itself."""
    below = np.searchsorted(reference, values, side="left")
    equal = np.searchsorted(reference, values, side="right") - below - leave_one_out
    return (below + 0.5 * equal + 0.5) / (reference.size + 1 - leave_one_out)


class FlatnessReference:
    """Per channel and feature the calibration's sorted values; per object its flatness."""

    def __init__(self, table: ScoreTable, channels: int) -> None:
        self._sorted = sorted_features(table, channels)
        self._blocks = {
            b.object_name: [np.asarray(b.features[name], dtype=np.float64) for name in HEATMAP_FEATURES]
            for b in table.objects
        }
        self._keypoints = {b.object_name: np.asarray(b.keypoint_ids, dtype=int) for b in table.objects}
        self._flatness: dict[tuple[str, tuple[int, ...]], np.ndarray] = {}

    def instance_z(self, instance: InstanceFeatures) -> float | None:
        """z of the instance's flatness among the calibration instances' (None: nothing to rank)."""
        used = tuple(p for p in range(len(HEATMAP_FEATURES)) if np.isfinite(instance.features[:, p]).all())
        if not used or instance.object not in self._blocks:
            return None
        scores = []
        for p in used:
            values = zip(instance.channels, instance.features[:, p], strict=True)
            ranks = np.array([_ranks(self._sorted[p][int(channel)], value) for channel, value in values])
            scores.append(SIGNS[HEATMAP_FEATURES[p]] * _normal_scores(ranks))
        reference = self._reference_flatness(instance.object, used)
        if reference.size == 0:
            return None
        return _NORMAL.inv_cdf(_ranks(reference, float(np.mean(scores))))

    def _reference_flatness(self, name: str, used: tuple[int, ...]) -> np.ndarray:
        key = (name, used)
        if key not in self._flatness:
            scores = []
            for p in used:
                matrix = self._blocks[name][p]
                ranks = [
                    _ranks(self._sorted[p][int(channel)], matrix[:, column], leave_one_out=True)
                    for column, channel in enumerate(self._keypoints[name])
                ]
                scores.append(SIGNS[HEATMAP_FEATURES[p]] * _normal_scores(np.stack(ranks, axis=1)))
            flatness = np.mean(scores, axis=(0, 2))
            self._flatness[key] = np.sort(flatness[np.isfinite(flatness)])
        return self._flatness[key]


def _normal_scores(ranks: np.ndarray) -> np.ndarray:
    clipped = np.clip(ranks, 1e-9, 1 - 1e-9)
    return np.vectorize(_NORMAL.inv_cdf, otypes=[float])(clipped)


def look_statistic(look: list[float]) -> float | None:
    """A look's Z from the z of its instances (None: none to rank)."""
    if not look:
        return None
    m = len(look)
    return sum(look) / math.sqrt(m * (1 + (m - 1) * WITHIN_FRAME_CORRELATION))


class SequentialAlarm:
    """Two e-CUSUMs over the looks' Z (flatter and sharper heatmaps than the calibration's)."""

    def __init__(self, alarm_level: float) -> None:
        self.threshold = 2.0 / alarm_level
        self.looks = 0
        self._cusums = [1.0, 1.0]

    def observe(self, look: list[float]) -> None:
        z = look_statistic(look)
        if z is not None:
            self.observe_statistic(z)

    def observe_statistic(self, z: float) -> None:
        """One look, by its Z: looks of several replicas merge in time order."""
        for side, sign in enumerate((1.0, -1.0)):
            log_e = sign * LAMBDA * z - LAMBDA**2 / 2
            self._cusums[side] = math.exp(min(log_e + math.log(max(self._cusums[side], 1.0)), 700.0))
        self.looks += 1

    @property
    def evidence(self) -> float:
        return max(self._cusums)

    @property
    def alarm(self) -> bool:
        return self.evidence >= self.threshold
