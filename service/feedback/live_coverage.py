"""Live labelled coverage: what the field's labels say of each calibration version's sets so far.

Read top-down, ``live_coverage``: the labelled predictions (from the store, so every replica
reports the same), each stream's frames grouped into looks (service.monitoring.looks: frames of one
scene are one observation, not many), then per group (the version's answers as a whole, per
object, per keypoint, per camera stream, per caller group, per Mondrian stratum) the raw
coverage of its labelled keypoints, one vote per look (the share covered among the look's first
labelled frame's keypoints of the group), the confidence sequence of the votes' mean, and the
alarm (a betting e-process) once coverage is proven below the version's promise
(service.feedback.confidence_sequence).

With ``coverage: object`` a unit is an instance whose keypoints were all labelled: covered when
every one of them is in its set (what the object guarantee speaks about).

A stratum group (answers asked with ``stratify``) gathers the units its stratum's thresholds
served, across keypoints (difficulty bins are fitted per keypoint: "difficulty bin 2" is each
keypoint's bin 2); each unit's floor is its own stratum's (n, t), so the alarm tests each
stratum threshold's own promise, and ``pooled`` gathers the rows that fell back to the pooled one.
"""

from __future__ import annotations

import time
from collections.abc import Iterable, Iterator
from dataclasses import dataclass, field
from typing import Any

import numpy as np

from calibration_store import RetainedPrediction
from service.feedback.confidence_sequence import BettingAlarm, coverage_bounds, promised_floor
from service.feedback.labels import covered_units
from service.monitoring.looks import Frame, LookTracker


@dataclass(frozen=True)
class Unit:
    """One judged keypoint (or instance, object scope) of a labelled prediction."""

    object: str
    keypoint: str | None
    stream: str
    group: str | None
    stratum: str | None  # the Mondrian stratum whose threshold served it (None: not stratified)
    covered: bool
    floor: float


@dataclass
class _Votes:
    promised: float
    alarm: BettingAlarm
    floor: float = 1.0
    labelled: int = 0
    covered: int = 0
    total: float = 0.0
    looks: set[tuple[str, int]] = field(default_factory=set)


@dataclass(frozen=True)
class GroupCoverage:
    """The coverage of one group so far, its confidence sequence and its alarm."""

    level: str
    name: str
    version: int
    guarantee: str  # exchangeable (the calibration's), or adaptive (ACI: no floor, no alarm)
    nonconformity: str
    coverage: str
    epsilon: float
    delta: float | None
    labelled: int
    covered: int
    looks: int
    look_mean: float | None
    lower: float
    upper: float
    promised: float
    floor: float
    alarm: bool


def live_coverage(
    store: Any, model_hash: str, keypoint_names: list[str], limit: int, level: float
) -> list[GroupCoverage]:
    """Every group's live coverage from the newest ``limit`` labelled predictions; ``level`` is
    the false-alarm probability of each group's alarm (half to the sequence, half to the band)."""
    labelled = store.labelled_predictions(model_hash, limit)
    looks = look_of(labelled)
    groups: dict[tuple, _Votes] = {}
    for prediction in labelled:
        record = prediction.record
        query = record["query"]
        guarantee = "exchangeable" if record.get("adaptive") is None else "adaptive"
        base = (
            prediction.version,
            guarantee,
            query["nonconformity"],
            query["coverage"],
            query["epsilon"],
            query["delta"],
        )
        look = looks[prediction.id]
        by_group: dict[tuple, list[Unit]] = {}
        band = level / 2 if guarantee == "exchangeable" else 0.0  # ACI promises a long-run bound instead
        for unit in units(record, prediction.labels or {}, keypoint_names, band, prediction.stream):
            for name_level, name in _names(unit):
                by_group.setdefault((*base, name_level, name), []).append(unit)
        for key, members in by_group.items():
            votes = groups.setdefault(key, _Votes(1.0 - query["epsilon"], BettingAlarm(level)))
            votes.labelled += len(members)
            votes.covered += sum(u.covered for u in members)
            votes.floor = min([votes.floor, *(u.floor for u in members)])
            if look not in votes.looks:
                votes.looks.add(look)
                vote = float(np.mean([u.covered for u in members]))
                votes.total += vote
                votes.alarm.observe(vote, float(np.mean([u.floor for u in members])))
    return [_report(key, votes, level) for key, votes in sorted(groups.items(), key=lambda kv: str(kv[0]))]


def look_of(labelled: Iterable[RetainedPrediction]) -> dict[str, tuple[str, int]]:
    """Each prediction's look: (stream, number), replaying each stream's frames in serving order."""
    trackers: dict[str, LookTracker] = {}
    numbers: dict[str, int] = {}
    looks = {}
    for prediction in sorted(labelled, key=lambda p: (p.created_at, p.id)):
        stream = prediction.stream or f"client:{prediction.record.get('client', '')}"
        instances = prediction.record["instances"]
        frame = Frame(tuple(i["object"] for i in instances), np.array([i["bbox"] for i in instances]))
        if trackers.setdefault(stream, LookTracker()).is_new_look(frame) or stream not in numbers:
            numbers[stream] = numbers.get(stream, -1) + 1
        looks[prediction.id] = (stream, numbers[stream])
    return looks


def units(
    record: dict[str, Any], labels: dict[str, Any], keypoint_names: list[str], band: float, stream: str
) -> Iterator[Unit]:
    """The judged units of one labelled prediction (keypoints, or whole instances: object scope)."""
    rows, instances = record["rows"], record["instances"]
    for index, row, covered in covered_units(record, labels.get("rows", [])):
        members = [r for r, kept in enumerate(rows) if kept["instance"] == index] if row is None else [row]
        floor = min(_floor(rows[r]["guarantee"], band) for r in members)
        name = None if row is None else keypoint_names[rows[row]["channel"]]
        strata = {rows[r].get("stratum") for r in members}  # one per instance with coverage object
        stratum = strata.pop() if len(strata) == 1 else None
        instance = instances[index]
        yield Unit(instance["object"], name, stream, instance["group"], stratum, covered, floor)


def _floor(guarantee: dict[str, Any], band: float) -> float:
    if band == 0.0:
        return 0.0
    return promised_floor(guarantee["n"], guarantee["t"], guarantee["epsilon"], guarantee["delta"], band)


def _names(unit: Unit) -> Iterator[tuple[str, str]]:
    yield "version", "all"
    yield "object", unit.object
    if unit.keypoint is not None:
        yield "keypoint", f"{unit.object}/{unit.keypoint}"
    if unit.stream:
        yield "stream", unit.stream
    if unit.group:
        yield "group", unit.group
    if unit.stratum is not None:
        yield "stratum", unit.stratum


def _report(key: tuple, votes: _Votes, level: float) -> GroupCoverage:
    version, guarantee, nonconformity, coverage, epsilon, delta, name_level, name = key
    count = len(votes.looks)
    bounds = coverage_bounds(votes.total, count, level)
    return GroupCoverage(
        level=name_level,
        name=name,
        version=version,
        guarantee=guarantee,
        nonconformity=nonconformity,
        coverage=coverage,
        epsilon=epsilon,
        delta=delta,
        labelled=votes.labelled,
        covered=votes.covered,
        looks=count,
        look_mean=bounds.mean,
        lower=bounds.lower,
        upper=bounds.upper,
        promised=votes.promised,
        floor=votes.floor,
        alarm=votes.alarm.raised,
    )


class LiveCoverageReader:
    """``live_coverage`` of one model, for the admin API (fresh) and /metrics (cached a few seconds)."""

    def __init__(
        self, store: Any, model_hash: str, keypoint_names: list[str], limit: int, level: float
    ) -> None:
        self._arguments = (store, model_hash, keypoint_names, limit, level)
        self.level = level
        self._cached: tuple[float, list[GroupCoverage]] | None = None

    def report(self, max_age_s: float = 0.0) -> list[GroupCoverage]:
        now = time.monotonic()
        if self._cached is None or now - self._cached[0] > max_age_s:
            self._cached = (now, live_coverage(*self._arguments))
        return self._cached[1]
