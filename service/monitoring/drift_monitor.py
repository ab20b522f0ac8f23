"""Label-free drift: each keypoint's heatmap features (p*, gamma, anisotropy) on live traffic against
the active version's calibration images (the guarantee needs exchangeable test images), by ``test``:
``sequential`` (default), the e-CUSUM over independent looks (looks.py), per-keypoint KS (Holm) saying
where while it alarms; ``ks``, Holm over every keypoint x feature at ``alarm_level``; ``psi``, the
population stability index above ``PSI_THRESHOLD`` once a window holds ``PSI_MIN_LIVE`` values.
Tests run when the report is read (cached); a fleet shares its state (drift_shares.py, fleet_looks.py).
"""

from __future__ import annotations

import logging
import math
import os
import random
import threading
import time
from collections import deque
from collections.abc import Callable, Iterable
from dataclasses import dataclass, field, replace
from typing import Literal

import numpy as np

from calibration_store import ScoreTable, StoreError
from service.conformal import HeatmapStatistics
from service.conformal.features import HEATMAP_FEATURES, heatmap_features
from service.detector.manifest import Manifest
from service.infra.metrics import drift_process_values
from service.monitoring.drift_shares import DriftShare, DriftShares, encode_share
from service.monitoring.fleet_looks import CONTINUED, ReplicaLooks, fleet_statuses, settle
from service.monitoring.looks import (
    FlatnessReference,
    Frame,
    InstanceFeatures,
    LookTracker,
    SequentialAlarm,
    SequentialState,
    look_statistic,
    sorted_features,
)
from service.monitoring.multiple_testing import holm_rejections
from service.monitoring.set_sizes import KINDS, KindSizes, set_sizes, shape_entries
from service.monitoring.two_sample import (
    ks_p_value,
    ks_statistic,
    population_stability_index,
    quantile_bin_edges,
)
from service.monitoring.windows import RingWindows

log = logging.getLogger(__name__)

DriftTest = Literal["sequential", "ks", "psi"]
#: psi: a feature alarms above this index
PSI_THRESHOLD = 0.25
#: share of requests that also compute the statistics their score skips, so every feature gets values
FULL_STATISTICS_SHARE = 0.25
#: seconds between two points of the history
HISTORY_SECONDS = 60.0
#: live values before PSI may alarm: its small-sample bias (bins - 1)(1/n + 1/m) is 0.11 at n = 100
PSI_MIN_LIVE = 400
_SHAPE_COLUMNS = slice(len(HEATMAP_FEATURES), len(HEATMAP_FEATURES) + 3)
_KIND_COLUMN = len(HEATMAP_FEATURES) + 3
_COLUMNS = _KIND_COLUMN + 1
#: looks waiting for the next evaluation (the history ticker evaluates once a minute)
MAX_PENDING_LOOKS = 100_000
#: points kept in the history (6 h at one a minute)
HISTORY_POINTS = 360
#: looks (time, Z, status, key) a process keeps to share: a fleet's sequential alarm runs over them
SHARED_LOOKS = 10_000
#: frames (time, objects, boxes) a process keeps to share, to tell other replicas' looks from
#: continuations of its frames (several intervals at 300 frames/s)
SHARED_FRAMES = 5_000

#: the active version and its scores (None, None when there is none or it cannot serve)
ReferenceSource = Callable[[], tuple[int | None, ScoreTable | None]]


@dataclass(frozen=True)
class DriftSettings:
    window: int  # live values kept per keypoint and feature
    test: DriftTest
    alarm_level: float  # ks: family-wise error of the Holm family; sequential: 1 / looks
    full_statistics_share: float = FULL_STATISTICS_SHARE
    history_seconds: float = HISTORY_SECONDS


@dataclass(frozen=True)
class FeatureTest:
    """One two-sample comparison; statistic and p_value are None while a side has no data."""

    statistic: float | None
    p_value: float | None  # ks only
    alarm: bool
    live_n: int
    reference_n: int


@dataclass(frozen=True)
class KeypointDrift:
    object: str
    keypoint: str
    index: int
    features: dict[str, FeatureTest]


@dataclass(frozen=True)
class ObjectDrift:
    """Per feature: its keypoints' largest statistic, Bonferroni p-value, and any alarm."""

    object: str
    keypoints: list[int]
    features: dict[str, FeatureTest]
    alarm: bool


@dataclass(frozen=True)
class HistoryPoint:
    time: float  # unix seconds
    version: int | None
    recorded: int  # live values recorded so far (all windows)
    alarm: bool
    alarms: int  # keypoint x feature alarms
    keypoint_statistics: list[float | None]  # per manifest channel: largest statistic over features
    object_statistics: dict[str, float | None]


@dataclass(frozen=True)
class DriftReport:
    version: int | None  # the reference: the active calibration version
    reference_available: bool
    reason: str | None  # why there is no reference (None when there is)
    window: int
    test: DriftTest
    alarm_threshold: float
    alarm: bool
    keypoints: list[KeypointDrift]
    objects: list[ObjectDrift]
    set_sizes: dict[str, KindSizes]
    recorded: int
    evaluated_at: float
    process: int
    sequential: SequentialState | None = None  # the sequential test's state (test sequential)
    history: list[HistoryPoint] = field(default_factory=list)
    replicas: int = 1  # the processes whose windows this report covers (this one included)
    oldest_share_seconds: float = 0.0  # age of the oldest other replica's contribution


@dataclass(frozen=True)
class _Reference:
    """[feature][channel]: sorted calibration values and PSI bin edges (None: no values)."""

    version: int
    values: list[list[np.ndarray | None]]
    edges: list[list[np.ndarray | None]]


class DriftMonitor:
    """Live windows of every keypoint's features, tested lazily against the active version."""

    def __init__(
        self,
        manifest: Manifest,
        reference: ReferenceSource,
        settings: DriftSettings,
        shares: DriftShares | None = None,
    ) -> None:
        if settings.test == "psi" and settings.window < PSI_MIN_LIVE:
            never = (
                "drift: psi alarms need %d live values per window; CKS_DRIFT_WINDOW is %d, so it never alarms"
            )
            log.warning(never, PSI_MIN_LIVE, settings.window)
        self.settings = settings
        self._manifest = manifest
        self._source = reference
        self._channels = manifest.num_keypoints
        # per channel, one row per live instance: features (NaN: not computed), set shape entries, kind
        self._windows = RingWindows(self._channels, settings.window, width=_COLUMNS)
        # sequential: the rows of the looks' first frames only, for the per-keypoint tests
        self._look_windows = RingWindows(self._channels, settings.window, width=_COLUMNS)
        self._object_of = {spec.index: spec.object for spec in manifest.keypoints}
        self._first_channels = np.array([manifest.object(k.object).keypoints[0] for k in manifest.keypoints])
        self._looks = LookTracker()
        self._pending: deque[tuple[float, int, list[InstanceFeatures]]] = deque(maxlen=MAX_PENDING_LOOKS)
        self._shares = shares  # where the replicas of a fleet meet (None: this process alone)
        # looks tested against the current version: (time, Z, fleet status, look key)
        self._looks_seen: deque[tuple[float, float, float, int]] = deque(maxlen=SHARED_LOOKS)
        self._frame_log: deque[tuple[float, Frame]] = deque(maxlen=SHARED_FRAMES)
        self._complete_since = 0.0  # the newest frame dropped from the log
        self._continues_others = False  # some of its looks continue another replica's: the fleet's count
        self._taken_over: list[DriftShare] = []  # of stopped processes: their looks join ours
        self._frames = 0
        self._look_lock = threading.Lock()
        self._sequential: SequentialAlarm | None = None
        self._flatness: tuple[int, FlatnessReference] | None = None
        self._reference: _Reference | None = None
        self._evaluation_lock = threading.Lock()
        self._cached: tuple[tuple, DriftReport] | None = None
        self._history: deque[HistoryPoint] = deque(maxlen=HISTORY_POINTS)
        self._stop = threading.Event()
        self._ticker: threading.Thread | None = None
        self._sharer: threading.Thread | None = None

    def wants_all_statistics(self) -> bool:
        """Whether this request should compute every heatmap statistic, not only its score's."""
        return random.random() < self.settings.full_statistics_share

    def record(
        self,
        channels: np.ndarray,
        statistics: HeatmapStatistics,
        kind: str,
        shapes: np.ndarray,
        frame: Frame | None = None,
    ) -> None:
        """Keep one request's features and set shapes; ``frame`` tells a new look (None: always one)."""
        rows = np.empty((channels.size, _COLUMNS))
        rows[:, : len(HEATMAP_FEATURES)] = live_features(statistics)
        rows[:, _SHAPE_COLUMNS] = shape_entries(shapes)
        rows[:, _KIND_COLUMN] = KINDS.index(kind)
        self._windows.append(channels, rows)
        if self.settings.test != "sequential":
            return
        with self._look_lock:
            self._frames += 1
            seen = time.time()
            if frame is not None:
                if len(self._frame_log) == SHARED_FRAMES:
                    self._complete_since = self._frame_log[0][0]
                self._frame_log.append((seen, frame))
            key = self._looks.new_look_key(frame)
            if key is None:
                return
            self._pending.append((seen, key, self._instances(channels, rows[:, : len(HEATMAP_FEATURES)])))
        self._look_windows.append(channels, rows)

    def _instances(self, channels: np.ndarray, features: np.ndarray) -> list[InstanceFeatures]:
        """The request's rows split by instance (each instance's channels come in manifest order)."""
        starts = np.flatnonzero(channels == self._first_channels[channels])
        ends = [*starts[1:], channels.size]
        return [
            InstanceFeatures(self._object_of[int(channels[a])], channels[a:b], features[a:b])
            for a, b in zip(starts, ends, strict=True)
        ]

    def report(self) -> DriftReport:
        """The tests of every window (the fleet's) against the active version (cached)."""
        version, table = self._source()
        others = [] if self._shares is None else self._shares.others()
        key = (version, self._windows.written(), tuple((o.replica, o.updated_at) for o in others))
        with self._evaluation_lock:
            if self._cached is None or self._cached[0] != key:
                self._cached = (key, self._evaluate(version, table, key[1], others))
            report, history = self._cached[1], list(self._history)
        oldest = max((time.time() - share.updated_at for share in others), default=0.0)
        return replace(report, history=history, oldest_share_seconds=oldest)

    def start(self) -> None:
        """Add a history point every ``history_seconds``; in a fleet, take over and share windows."""
        self._ticker = threading.Thread(target=self._tick_forever, name="drift-history", daemon=True)
        self._ticker.start()
        if self._shares is not None:
            try:  # before any request is recorded: the looks taken over come first
                self._take_over(self._shares.take_over_stopped())
                self._shares.publish(self._share())  # its row says it is in the fleet
            except StoreError as error:
                log.warning("drift: the windows of stopped processes could not be taken over (%s)", error)
            self._sharer = threading.Thread(target=self._share_forever, name="drift-share", daemon=True)
            self._sharer.start()

    def stop(self) -> None:
        self._stop.set()
        for thread in (self._ticker, self._sharer):
            if thread is not None:
                thread.join(timeout=5.0)

    def share(self) -> None:
        """Write this process's windows and looks to the store (those now decided for good)."""
        assert self._shares is not None
        self.report()  # tests the pending looks: their Z are shared
        self._settle(self._shares.others())
        self._shares.publish(self._share())
        drift_process_values().set(self._windows.written())

    def _share_forever(self) -> None:
        assert self._shares is not None
        while True:
            stopping = self._stop.wait(self._shares.interval)
            try:
                self.share()
            except StoreError as error:
                log.warning("drift: this process's windows could not be shared (%s)", error)
            except Exception:
                log.exception("drift: sharing this process's windows failed")
            if stopping:
                return

    def _share(self) -> bytes:
        seen = self._replica_looks()
        with self._look_lock:
            frames = self._frames
        version, recorded = self._version(), self._windows.written()
        windows = [[w.window(c) for c in range(self._channels)] for w in (self._windows, self._look_windows)]
        return encode_share(version, frames, recorded, *windows, seen)

    def _version(self) -> int | None:
        """The version this process's looks were tested against."""
        return None if self._flatness is None else self._flatness[0]

    def _replica_looks(self) -> ReplicaLooks:
        """This process's frames and looks (the lock held only to copy them: requests wait on it)."""
        with self._look_lock:
            looks, frames = list(self._looks_seen), list(self._frame_log)
            covered_until = self._pending[0][0] if self._pending else time.time()
            complete_since = self._complete_since
        return ReplicaLooks(
            replica="" if self._shares is None else self._shares.replica,
            covered_until=covered_until,
            complete_since=complete_since,
            frame_times=np.array([seen for seen, _ in frames], dtype=np.float64),
            frames=tuple(frame for _, frame in frames),
            looks=np.array([look[:2] for look in looks], dtype=np.float64).reshape(-1, 2),
            statuses=np.array([look[2] for look in looks], dtype=np.float64),
            keys=np.array([look[3] for look in looks], dtype=np.int64),
        )

    def _settle(self, others: list[DriftShare]) -> None:
        """Decide for good the fleet status of the looks every replica's frames now decide."""
        assert self._shares is not None
        with self._evaluation_lock:  # no look is added meanwhile
            own = self._replica_looks()  # every replica's frames count, whatever its version
            statuses = settle(own, [share.seen for share in others], self._shares.read_at)
            with self._look_lock:
                looks = zip(self._looks_seen, statuses.tolist(), strict=True)
                decided = ((seen, z, status, key) for (seen, z, _, key), status in looks)
                self._looks_seen = deque(decided, maxlen=SHARED_LOOKS)
            self._continues_others = self._continues_others or bool((statuses == CONTINUED).any())
            self._cached = None

    def _take_over(self, stopped: list[DriftShare]) -> None:
        """Continue the windows, looks and frames of stopped processes of this host as this one's."""
        for share in stopped:
            for target, windows in ((self._windows, share.windows), (self._look_windows, share.look_windows)):
                for channel, rows in enumerate(windows[: self._channels]):
                    if rows.shape[1:] == (_COLUMNS,):
                        target.append(np.full(rows.shape[0], channel, dtype=np.int64), rows)
            self._taken_over.append(share)
        seen = (zip(s.seen.frame_times, s.seen.frames, strict=True) for s in stopped)
        frames = sorted(((float(t), frame) for pairs in seen for t, frame in pairs), key=lambda item: item[0])
        with self._look_lock:
            self._frames += sum(share.frames for share in stopped)
            self._frame_log.extend(frames)
            self._complete_since = max([self._complete_since, *(s.seen.complete_since for s in stopped)])
            keys = [key for share in stopped for key in share.seen.keys.tolist()]
            self._looks.remember([frame for _, frame in frames], keys)
        if stopped:
            log.info("drift: took over the windows of %d stopped process(es) of this host", len(stopped))

    def _tick_forever(self) -> None:
        last_recorded = -1
        while not self._stop.wait(self.settings.history_seconds):
            try:
                report = self.report()
            except Exception:  # a store hiccup or a bug: the history skips a point, requests go on
                log.exception("drift history: the evaluation failed")
                continue
            if report.recorded != last_recorded:
                last_recorded = report.recorded
                with self._evaluation_lock:
                    self._history.append(_history_point(report))

    def _evaluate(
        self, version: int | None, table: ScoreTable | None, recorded: int, others: list[DriftShare]
    ) -> DriftReport:
        reference, reason = self._reference_for(version, table)
        sequential = self._sequential_state(version, table if reference is not None else None)
        if sequential is not None and (others or self._continues_others):
            sequential = self._fleet_sequential(sequential, others)
        windows = self._merged(self._windows, [share.windows for share in others])
        look_windows = [share.look_windows for share in others]
        tested = windows if sequential is None else self._merged(self._look_windows, look_windows)
        live = [[w[np.isfinite(w[:, p]), p] for w in tested] for p in range(len(HEATMAP_FEATURES))]
        tests = self._tests(reference, live, sequential is None or sequential.alarm)
        by_channel = [dict(zip(HEATMAP_FEATURES, column, strict=True)) for column in zip(*tests, strict=True)]
        keypoints = [
            KeypointDrift(k.object, k.name, k.index, by_channel[k.index]) for k in self._manifest.keypoints
        ]
        objects = [_object_drift(obj.name, list(obj.keypoints), keypoints) for obj in self._manifest.objects]
        rows, settings = np.concatenate(windows), self.settings
        return DriftReport(
            version=version,
            reference_available=reference is not None,
            reason=reason,
            window=settings.window,
            test=settings.test,
            alarm_threshold=PSI_THRESHOLD if settings.test == "psi" else settings.alarm_level,
            alarm=any(o.alarm for o in objects) if sequential is None else sequential.alarm,
            keypoints=keypoints,
            objects=objects,
            set_sizes=set_sizes(rows[:, _KIND_COLUMN].astype(int), rows[:, _SHAPE_COLUMNS]),
            recorded=recorded + sum(share.recorded for share in others),
            evaluated_at=time.time(),
            process=os.getpid(),
            sequential=sequential,
            replicas=1 + len(others),
        )

    def _merged(self, own: RingWindows, others: list[list[np.ndarray]]) -> list[np.ndarray]:
        """Per channel: this process's window and those of the other replicas, one after another."""
        merged = []
        for channel in range(self._channels):
            parts = [own.window(channel)]
            parts += [w[channel] for w in others if channel < len(w) and w[channel].shape[1:] == (_COLUMNS,)]
            merged.append(np.concatenate(parts) if len(parts) > 1 else parts[0])
        return merged

    def _sequential_state(self, version: int | None, table: ScoreTable | None) -> SequentialState | None:
        """Test the looks recorded since the last evaluation; a new active version starts afresh."""
        if self.settings.test != "sequential":
            return None
        with self._look_lock:
            pending = list(self._pending)
            self._pending.clear()
            frames = self._frames
        if table is None or version is None:
            self._flatness, self._sequential = None, None
        else:
            if self._flatness is None or self._flatness[0] != version:
                self._flatness = (version, FlatnessReference(table, self._channels))
                self._sequential = SequentialAlarm(self.settings.alarm_level)
                self._replay_taken_over(version)
            flatness, alarm = self._flatness[1], self._sequential
            assert alarm is not None
            for seen, key, look in pending:
                z = look_statistic([z for z in map(flatness.instance_z, look) if z is not None])
                if z is not None:
                    alarm.observe_statistic(z)
                    with self._look_lock:
                        self._looks_seen.append((seen, z, math.nan, key))
        alarm = self._sequential or SequentialAlarm(self.settings.alarm_level)  # none: no evidence
        return SequentialState(alarm.looks, frames, alarm.evidence, alarm.threshold, alarm.alarm)

    def _replay_taken_over(self, version: int) -> None:
        """A new reference: the taken-over looks tested against this version go first, in time order."""
        assert self._sequential is not None
        looks = sorted(
            (float(seen), float(z), float(status), int(key))
            for taken in (share.seen for share in self._taken_over if share.version == version)
            for (seen, z), status, key in zip(taken.looks, taken.statuses, taken.keys, strict=True)
        )
        with self._look_lock:
            self._looks_seen.clear()
            self._looks_seen.extend(looks)
        for _, z, status, _ in looks:
            if status != CONTINUED:
                self._sequential.observe_statistic(z)
            self._continues_others = self._continues_others or status == CONTINUED
        self._taken_over = []

    def _fleet_sequential(self, own: SequentialState, others: list[DriftShare]) -> SequentialState:
        """The alarm over the looks every replica tested against this version that count for the fleet."""
        version = self._version()
        fleet = [self._replica_looks(), *(share.seen for share in others)]
        statuses = fleet_statuses(fleet)  # every replica's frames count, whatever its version
        tested = [True, *(share.version == version for share in others)]
        counted = zip(fleet, statuses, tested, strict=True)
        merged = np.concatenate([replica.counted(status) for replica, status, same in counted if same])
        alarm = SequentialAlarm(self.settings.alarm_level)
        for z in merged[np.argsort(merged[:, 0], kind="stable"), 1]:
            alarm.observe_statistic(float(z))
        frames = own.frames + sum(share.frames for share in others)
        return replace(own, looks=alarm.looks, frames=frames, evidence=alarm.evidence, alarm=alarm.alarm)

    def _tests(
        self, reference: _Reference | None, live: list[list[np.ndarray]], may_alarm: bool
    ) -> list[list[FeatureTest]]:
        """[feature][channel] tests; alarms where Holm rejects over all (sequential: while it alarms)."""
        rows = [
            [self._test(reference, p, c, values) for c, values in enumerate(row)]
            for p, row in enumerate(live)
        ]
        if self.settings.test == "psi":
            return rows
        p_values = np.array([[math.nan if t.p_value is None else t.p_value for t in row] for row in rows])
        alarms = holm_rejections(p_values, self.settings.alarm_level)
        return [
            [replace(t, alarm=bool(alarm) and may_alarm) for t, alarm in zip(row, alarm_row, strict=True)]
            for row, alarm_row in zip(rows, alarms, strict=True)
        ]

    def _test(
        self, reference: _Reference | None, position: int, channel: int, live: np.ndarray
    ) -> FeatureTest:
        values = None if reference is None else reference.values[position][channel]
        n = 0 if values is None else values.size
        if reference is None or values is None or n == 0 or live.size == 0:
            return FeatureTest(None, None, False, live.size, n)
        if self.settings.test == "psi":
            score = population_stability_index(values, live, reference.edges[position][channel])
            alarm = live.size >= PSI_MIN_LIVE and score > PSI_THRESHOLD
            return FeatureTest(score, None, alarm, live.size, n)
        statistic = ks_statistic(values, live)
        return FeatureTest(statistic, ks_p_value(statistic, live.size, n), False, live.size, n)

    def _reference_for(
        self, version: int | None, table: ScoreTable | None
    ) -> tuple[_Reference | None, str | None]:
        if version is None:
            return None, "no calibration version is active for this model"
        if table is None:
            return None, f"the active calibration version {version} cannot serve this model's manifest"
        missing = [block.object_name for block in table.objects if not block.has_features]
        if missing or not table.objects:
            return None, (
                f"the active calibration version {version} carries no heatmap features (made before they"
                " were stored): recalibrate, or append a batch to it, to get a drift reference"
            )
        if self._reference is None or self._reference.version != version:
            values = sorted_features(table, self._channels)
            edges = [
                [None if v is None or not v.size else quantile_bin_edges(v) for v in row] for row in values
            ]
            self._reference = _Reference(version, values, edges)
        return self._reference, None


def live_features(statistics: HeatmapStatistics) -> np.ndarray:
    """(rows, features): those ``statistics`` allow (p* needs the peak, the others the spread), else NaN."""
    rows = statistics.uninformative.size
    has_peak, has_spread = statistics.peak_probability is not None, statistics.covariance is not None
    placeholders = replace(  # a part not computed gets a placeholder, its features dropped after
        statistics,
        peak_probability=statistics.peak_probability if has_peak else np.ones(rows),
        covariance=statistics.covariance if has_spread else np.broadcast_to(np.eye(2), (rows, 2, 2)),
    )
    features, nan = heatmap_features(placeholders), np.full(rows, np.nan)
    computed = [has_peak if name == "peak_probability" else has_spread for name in HEATMAP_FEATURES]
    return np.column_stack(
        [features[n] if c else nan for n, c in zip(HEATMAP_FEATURES, computed, strict=True)]
    )


def _largest(tests: Iterable[FeatureTest]) -> float | None:
    return max((t.statistic for t in tests if t.statistic is not None), default=None)


def _object_drift(name: str, channels: list[int], keypoints: list[KeypointDrift]) -> ObjectDrift:
    features = {}
    for feature in HEATMAP_FEATURES:
        tests = [keypoints[channel].features[feature] for channel in channels]
        p_values = [t.p_value for t in tests if t.p_value is not None]
        bonferroni = min(1.0, len(p_values) * min(p_values)) if p_values else None
        sizes = (min(t.live_n for t in tests), min(t.reference_n for t in tests))
        features[feature] = FeatureTest(_largest(tests), bonferroni, any(t.alarm for t in tests), *sizes)
    return ObjectDrift(name, channels, features, any(t.alarm for t in features.values()))


def _history_point(report: DriftReport) -> HistoryPoint:
    alarms = sum(t.alarm for k in report.keypoints for t in k.features.values())
    keypoints = [_largest(k.features.values()) for k in report.keypoints]
    objects = {o.object: _largest(o.features.values()) for o in report.objects}
    return HistoryPoint(
        time=report.evaluated_at,
        version=report.version,
        recorded=report.recorded,
        alarm=report.alarm,
        alarms=alarms,
        keypoint_statistics=keypoints,
        object_statistics=objects,
    )
