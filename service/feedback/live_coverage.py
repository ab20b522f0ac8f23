"""Live labelled coverage: what the field's labels say of each calibration version's sets so far.

Read top-down, ``CoverageFold.add``: each labelled prediction, as it is read, is split into its
judged units and counted per group (the version's answers as a whole, per object, per keypoint,
per camera stream, per caller group, per Mondrian stratum): the raw coverage of its labelled
keypoints, and one vote per look (frames of one scene are one observation, not many: the look
was fixed when the answer was served, service.feedback.retention), cast by the look's first
labelled frame (its share covered of the group's units). Each group's confidence sequence of the
votes' mean and its alarm (a betting e-process, once coverage is proven below the version's
promise) are service.feedback.confidence_sequence's.

``LiveCoverageReader`` keeps one fold per process and adds only the labels that are new since
its last read (``labelled_since`` lists ids, a cheap indexed read; only new records are fetched
and decoded): a read costs what arrived since the previous one, not the CKS_FEEDBACK_MAX_RETAINED
rows the store may keep (docs/feedback.md measures both). Votes are cast in the order the labels
are read (label order), each label once; a raised alarm stays raised though its rows are evicted.
A replica started later folds the labels the store still keeps, so replicas agree on the labels
kept, not on evicted history.

With ``coverage: object`` a unit is an instance whose keypoints were all labelled: covered when
every one of them is in its set (what the object guarantee speaks about).

A stratum group (answers asked with ``stratify``) gathers the units its stratum's thresholds
served, across keypoints (difficulty bins are fitted per keypoint: "difficulty bin 2" is each
keypoint's bin 2); each unit's floor is its own stratum's (n, t), so the alarm tests each
stratum threshold's own promise, and ``pooled`` gathers the rows that fell back to the pooled one.
"""

from __future__ import annotations

import logging
import threading
import time
from collections import OrderedDict
from collections.abc import Iterator
from dataclasses import dataclass
from datetime import datetime, timedelta
from typing import Any

import numpy as np

from calibration_store import RetainedPrediction, StoreError
from service.feedback.confidence_sequence import BettingAlarm, coverage_bounds, promised_floor
from service.feedback.labels import covered_units

log = logging.getLogger(__name__)
#: each read lists again the labels stamped this long before the newest one seen: a label stamped
#: earlier may commit later (a slow transaction, another replica's clock)
SETTLE = timedelta(seconds=60)
#: records fetched and decoded at once (the first read of a full store folds them page by page)
PAGE = 2000


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
    looks: int = 0
    reported: GroupCoverage | None = None  # its report, until it changes


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


class CoverageFold:
    """Every group's live coverage, label by label; ``level`` is the false-alarm probability of
    each group's alarm (half to the sequence, half to the band); the last ``looks_kept`` looks are
    remembered (a label of a look forgotten since votes again)."""

    def __init__(self, keypoint_names: list[str], level: float, looks_kept: int) -> None:
        self._names, self.level, self._looks_kept = keypoint_names, level, looks_kept
        self._groups: dict[tuple, _Votes] = {}
        self._voted: OrderedDict[str, None] = OrderedDict()

    def add(self, prediction: RetainedPrediction) -> None:
        """Count one labelled prediction: raw counts always, a vote if it opens its look."""
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
        by_group: dict[tuple, list[Unit]] = {}
        band = self.level / 2 if guarantee == "exchangeable" else 0.0  # ACI promises a long-run bound
        labels = prediction.labels or {}
        for unit in units(record, labels, self._names, band, prediction.stream):
            for name_level, name in _names(unit):
                by_group.setdefault((*base, name_level, name), []).append(unit)
        votes = self._opens_look(record.get("look", prediction.id))  # rows kept before looks: one each
        for key, members in by_group.items():
            group = self._groups.setdefault(key, _Votes(1.0 - query["epsilon"], BettingAlarm(self.level)))
            group.labelled += len(members)
            group.covered += sum(u.covered for u in members)
            group.floor = min([group.floor, *(u.floor for u in members)])
            group.reported = None
            if votes:
                vote = float(np.mean([u.covered for u in members]))
                group.looks += 1
                group.total += vote
                group.alarm.observe(vote, float(np.mean([u.floor for u in members])))

    def _opens_look(self, look: str) -> bool:
        if look in self._voted:
            self._voted.move_to_end(look)
            return False
        self._voted[look] = None
        if len(self._voted) > self._looks_kept:
            self._voted.popitem(last=False)
        return True

    def report(self) -> list[GroupCoverage]:
        for key, votes in self._groups.items():
            if votes.reported is None:
                votes.reported = _report(key, votes, self.level)
        return [votes.reported for _, votes in sorted(self._groups.items(), key=lambda kv: str(kv[0]))]


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
    count = votes.looks
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
    """The live coverage of one model, read incrementally from the store (see the module's doc):
    fresh for the admin API, cached a few seconds for /metrics."""

    def __init__(
        self, store: Any, model_hash: str, keypoint_names: list[str], looks_kept: int, level: float
    ) -> None:
        self._store, self._model_hash, self.level = store, model_hash, level
        self._fold = CoverageFold(keypoint_names, level, looks_kept)
        self._lock = threading.Lock()
        self._recent: dict[str, datetime] = {}  # ids folded, labelled within SETTLE of the newest
        self._newest: datetime | None = None
        self._cached: tuple[float, list[GroupCoverage]] | None = None

    def report(self, max_age_s: float = 0.0) -> list[GroupCoverage]:
        """Fold the labels new since the last read, then report. With ``max_age_s`` (/metrics,
        which must not wait: its scrape runs on the event loop), the last report is given at
        once (none before the first), and a fold is started in the background when it is older."""
        if max_age_s == 0.0:
            with self._lock:
                return self._fold_and_report()
        cached = self._cached
        if (cached is None or time.monotonic() - cached[0] > max_age_s) and self._lock.acquire(
            blocking=False
        ):
            threading.Thread(target=self._fold_in_background, name="live-coverage", daemon=True).start()
        return [] if cached is None else cached[1]

    def _fold_and_report(self) -> list[GroupCoverage]:
        report = self._fold.report() if self._fold_new() or self._cached is None else self._cached[1]
        self._cached = (time.monotonic(), report)
        return report

    def _fold_in_background(self) -> None:
        try:
            self._fold_and_report()
        except StoreError:  # the next scrape tries again
            log.warning("live coverage: the store could not be read", exc_info=True)
        finally:
            self._lock.release()

    def _fold_new(self) -> bool:
        """Fold what is new; whether anything was."""
        since = None if self._newest is None else self._newest - SETTLE
        listed = [
            (i, at) for i, at in self._store.labelled_since(self._model_hash, since) if i not in self._recent
        ]
        for start in range(0, len(listed), PAGE):
            page = listed[start : start + PAGE]
            found = {p.id: p for p in self._store.retained_predictions([i for i, _ in page])}
            for prediction_id, _ in page:
                if prediction_id in found:  # evicted in between: gone
                    self._fold.add(found[prediction_id])
            self._recent.update(page)  # folded: a store error on the next page refolds none of these
            self._newest = max(page[-1][1], self._newest or page[-1][1])
        if listed:
            self._recent = {i: at for i, at in self._recent.items() if at >= self._newest - SETTLE}
        return bool(listed)
