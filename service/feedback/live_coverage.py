"""Live labelled coverage: what the field's labels say of each calibration version's sets so far.
``CoverageFold`` counts each label's verdicts (verdicts.py) in its groups (version, object, keypoint,
stream, caller group, Mondrian stratum): raw coverage, and one vote per look (a scene's frames are one
observation), cast when its stream's next look is read (or the oldest beyond ``OPEN_LOOKS``). The
confidence sequences and alarms are confidence_sequence.py's (docs/feedback.md).
"""

from __future__ import annotations

import json
import logging
import threading
import time
from collections import OrderedDict
from dataclasses import dataclass, field
from datetime import datetime, timedelta
from typing import Any

import numpy as np

from calibration_store import LabelVerdicts, StoreError
from service.feedback.confidence_sequence import (
    CoverageAlarm,
    alarm_rungs,
    coverage_bounds,
    promised_floor,
    rung_floors,
)
from service.feedback.retention import LOOK_STREAMS
from service.feedback.verdicts import verdicts

log = logging.getLogger(__name__)
#: each read lists again the labels stamped this long before the newest one seen: a label stamped
#: earlier may commit later (a slow transaction, another replica's clock)
SETTLE = timedelta(seconds=60)
#: labels whose verdicts are fetched and decoded at once (a first read folds a full store page by page)
PAGE = 2000
#: verdict shapes kept parsed (the frames of a stream share one; beyond it the fold starts afresh)
SHAPES_KEPT = 4096
#: looks whose votes wait for the next look of their stream (one per stream the retention follows)
OPEN_LOOKS = LOOK_STREAMS


@dataclass(eq=False)  # kept by identity: an open look's tallies are keyed by their group
class _Votes:
    promised: float
    alarm: CoverageAlarm
    floor: float = 1.0
    labelled: int = 0
    covered: int = 0
    total: float = 0.0
    looks: int = 0
    reported: GroupCoverage | None = None  # its report, until it changes


@dataclass(frozen=True)
class GroupCoverage:
    version: int
    guarantee: str  # exchangeable (the calibration's), or adaptive (ACI: no floor, no alarm)
    nonconformity: str
    coverage: str
    epsilon: float
    delta: float | None
    level: str
    name: str
    labelled: int
    covered: int
    looks: int
    look_mean: float | None
    lower: float
    upper: float
    promised: float
    floor: float
    alarm: bool


@dataclass
class _Shape:
    """A verdict shape, parsed: per group its votes, units, their least floor and floors' sum per rung."""

    stream: str  # its stream group's name ("": none), whose next look completes a look of it
    groups: list[_Votes]
    units: list[int]
    least: list[float]
    floors: np.ndarray  # (groups, rungs): the sum of its units' floors on each rung of the alarm
    pending: list[list[int]] = field(default_factory=list)  # covered counts not yet added to the groups


@dataclass
class _OpenLook:
    """A look whose vote is not cast yet: per shape of its labels, the covered counts summed."""

    stream: str
    labels: dict[int, list] = field(default_factory=dict)  # id(shape): [shape, covered, labels]

    def add(self, shape: _Shape, covered: list[int]) -> None:
        entry = self.labels.setdefault(id(shape), [shape, np.zeros(len(covered), dtype=np.int64), 0])
        entry[1] += covered
        entry[2] += 1

    def cast(self) -> None:
        """One vote per group: the share covered of its units, against their mean floor (per rung)."""
        entries = list(self.labels.values())
        rows: dict[_Votes, int] = {}  # a group several shapes share is one row
        index = [rows.setdefault(group, len(rows)) for shape, _, _ in entries for group in shape.groups]
        # per group of each shape: covered, units, the floors' sum per rung
        parts = [
            np.column_stack([hits, n * np.asarray(shape.units), n * shape.floors])
            for shape, hits, n in entries
        ]
        counts = np.zeros((len(rows), parts[0].shape[1]))
        np.add.at(counts, index, np.concatenate(parts))
        votes = (counts[:, 0] / counts[:, 1]).tolist()
        floors = (counts[:, 2:] / counts[:, 1:2]).tolist()
        for group, vote, floor in zip(rows, votes, floors, strict=True):
            group.looks += 1
            group.total += vote
            group.alarm.observe(vote, floor)
            group.reported = None


class CoverageFold:
    """Every group's live coverage, label by label; the last ``looks_kept`` looks are remembered."""

    def __init__(self, level: float, looks_kept: int) -> None:
        self.level, self._looks_kept = level, looks_kept
        self._groups: dict[tuple, _Votes] = {}
        self._shapes: dict[str, _Shape] = {}
        self._voted: OrderedDict[str, None] = OrderedDict()
        self._open: OrderedDict[str, _OpenLook] = OrderedDict()
        self._open_by_stream: dict[str, str] = {}

    def add(self, verdicts: LabelVerdicts) -> None:
        """Count one label's verdicts: raw counts, and its look's vote while the look is open."""
        shape = self._shapes.get(verdicts.shape) or self._parse(verdicts.shape)
        covered = verdicts.tally["covered"]
        shape.pending.append(covered)
        look = verdicts.tally["look"]
        if look not in self._open and self._opens_look(look):
            previous = self._open_by_stream.pop(shape.stream, None)
            if previous is not None:
                self._open.pop(previous).cast()
            self._open[look] = _OpenLook(shape.stream)
            self._open_by_stream[shape.stream] = look
            if len(self._open) > OPEN_LOOKS:  # a stream that went quiet: its look is complete
                _, open_look = self._open.popitem(last=False)
                del self._open_by_stream[open_look.stream]
                open_look.cast()
        if look in self._open:
            self._open[look].add(shape, covered)

    def _parse(self, text: str) -> _Shape:
        if len(self._shapes) >= SHAPES_KEPT:  # labels of many shapes (streams, strata): start afresh
            self._count()
            self._shapes.clear()
        shape = json.loads(text)
        base = (shape["version"], shape["guarantee"], *shape["query"])
        exchangeable = shape["guarantee"] == "exchangeable"  # else ACI: a long-run bound, no floor
        nothing = (0.0,) * len(alarm_rungs(self.level))
        floors = [
            min(promised_floor(*g, self.level / 2) if exchangeable else 0.0 for g in guarantees)
            for guarantees in shape["floors"]
        ]
        ladders = [
            np.min([rung_floors(*g, self.level) if exchangeable else nothing for g in guarantees], axis=0)
            for guarantees in shape["floors"]
        ]
        stream = next((name for name_level, name, _ in shape["groups"] if name_level == "stream"), "")
        parsed = _Shape(stream, [], [], [], np.zeros(0))
        sums = []
        for name_level, name, runs in shape["groups"]:
            key = (*base, name_level, name)
            group = self._groups.get(key)
            if group is None:
                group = self._groups[key] = _Votes(1.0 - shape["query"][2], CoverageAlarm(self.level))
            members = [floor for floor, count in runs for _ in range(count)]
            parsed.groups.append(group)
            parsed.units.append(len(members))
            parsed.least.append(min(floors[floor] for floor in members))
            sums.append(np.sum([ladders[floor] for floor in members], axis=0))
        parsed.floors = np.array(sums).reshape(len(sums), len(alarm_rungs(self.level)))
        self._shapes[text] = parsed
        return parsed

    def _count(self) -> None:
        """Add the raw counts of the labels folded since the last time to their groups."""
        for shape in self._shapes.values():
            if shape.pending:
                covered = np.sum(np.array(shape.pending, dtype=np.int64), axis=0).tolist()
                labels = len(shape.pending)
                for group, units, hits, least in zip(
                    shape.groups, shape.units, covered, shape.least, strict=True
                ):
                    group.labelled += labels * units
                    group.covered += hits
                    group.floor = min(group.floor, least)
                    group.reported = None
                shape.pending.clear()

    def _opens_look(self, look: str) -> bool:
        if look in self._voted:
            self._voted.move_to_end(look)
            return False
        self._voted[look] = None
        if len(self._voted) > self._looks_kept:
            self._voted.popitem(last=False)
        return True

    def report(self) -> list[GroupCoverage]:
        self._count()
        for key, votes in self._groups.items():
            if votes.reported is None:
                votes.reported = _report(key, votes, self.level)
        return [votes.reported for _, votes in sorted(self._groups.items(), key=lambda kv: str(kv[0]))]


def _report(key: tuple, votes: _Votes, level: float) -> GroupCoverage:
    """``key``: (version, guarantee, nonconformity, coverage, epsilon, delta, level, name)."""
    bounds = coverage_bounds(votes.total, votes.looks, level)
    counts = (votes.labelled, votes.covered, votes.looks, bounds.mean, bounds.lower, bounds.upper)
    return GroupCoverage(*key, *counts, votes.promised, votes.floor, votes.alarm.raised)


class LiveCoverageReader:
    """The live coverage of one model, read incrementally from the store (see the module's doc)."""

    def __init__(self, store: Any, model_hash: str, names: list[str], looks_kept: int, level: float) -> None:
        self._store, self._model_hash, self._names, self.level = store, model_hash, names, level
        self._fold = CoverageFold(level, looks_kept)
        self._lock = threading.Lock()
        self._recent: dict[str, datetime] = {}  # ids folded, labelled within SETTLE of the newest
        self._newest: datetime | None = None
        self._cached: tuple[float, list[GroupCoverage]] | None = None

    def report(self, max_age_s: float = 0.0) -> list[GroupCoverage]:
        """Fold the new labels, then report (``max_age_s``: the last report at once, refreshed behind)."""
        if max_age_s == 0.0:
            with self._lock:
                return self._fold_and_report()
        cached = self._cached
        stale = cached is None or time.monotonic() - cached[0] > max_age_s
        if stale and self._lock.acquire(blocking=False):
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
        since = None if self._newest is None else self._newest - SETTLE
        listed = [
            (i, at) for i, at in self._store.labelled_since(self._model_hash, since) if i not in self._recent
        ]
        for start in range(0, len(listed), PAGE):
            page = listed[start : start + PAGE]
            found = self._verdicts([i for i, _ in page])
            for prediction_id, _ in page:
                if prediction_id in found:  # evicted in between: gone
                    self._fold.add(found[prediction_id])
            self._recent.update(page)  # folded: a store error on the next page refolds none of these
            self._newest = max(page[-1][1], self._newest or page[-1][1])
        if listed:
            self._recent = {i: at for i, at in self._recent.items() if at >= self._newest - SETTLE}
        return bool(listed)

    def _verdicts(self, ids: list[str]) -> dict[str, LabelVerdicts]:
        """The stored verdicts of ``ids`` (labels older than stored verdicts are judged here)."""
        found = self._store.label_verdicts(ids)
        missing = [i for i in ids if i not in found]
        if missing:
            found.update((p.id, verdicts(p, self._names)) for p in self._store.retained_predictions(missing))
        return found
