"""The served model's calibrations in memory: the active version with its scores, and cached
thresholds per (immutable) version. A poller reads the store's active version (how replicas see
each other's activations), so requests never wait on the store: while it is away the last good
state is served and ``health()`` says how stale it is.
"""

from __future__ import annotations

import logging
import math
import threading
import time
from collections import OrderedDict
from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from calibration_store import CalibrationStore, ScoreTable, StoreError, StoreUnavailable, VersionNotFound
from service.calibration.compatibility import version_incompatibility
from service.calibration.stratification import (
    DIFFICULTY,
    StratifiedThresholds,
    VersionStrata,
    describe_kinds,
    stratified_thresholds,
)
from service.conformal import (
    CoverageGuarantee,
    calibrate,
    calibrate_columns,
    coverage_guarantee,
    object_scores,
)
from service.detector.manifest import Manifest
from service.errors import Conflict, NotFound, StoreUnreachable, Unavailable

log = logging.getLogger(__name__)

#: score tables of versions other than the active one kept in memory
CACHED_TABLES = 8
#: how often the store is polled for a new active version
POLL_SECONDS = 1.0
#: longest wait for the store (its connection, statement, lock or round trip) before it counts as away
STORE_TIMEOUT_SECONDS = 1.5
_UNREACHABLE = "calibration store unreachable (%s); serving calibration version %s from memory"


@dataclass(frozen=True)
class ChannelThresholds:
    """One threshold and guarantee per manifest keypoint channel (``inf`` = unbounded)."""

    values: np.ndarray  # (K,) float64
    guarantees: tuple[CoverageGuarantee, ...]


def channel_thresholds(
    table: ScoreTable, num_keypoints: int, kind: str, scope: str, epsilon: float, delta: float | None
) -> ChannelThresholds:
    """Thresholds per keypoint channel (inf without data): per keypoint, or per object (``object``)."""
    values = np.full(num_keypoints, np.inf)
    guarantees = [coverage_guarantee(0, epsilon, delta)] * num_keypoints
    for block in table.objects:
        matrix, channels = block.scores[kind], block.keypoint_ids
        if scope == "object":
            calibration = calibrate(object_scores(matrix), epsilon, delta)
            block_values, block_guarantees = calibration.threshold, [calibration.guarantee] * len(channels)
        else:
            block_values, block_guarantees = calibrate_columns(matrix, epsilon, delta)
        values[channels] = block_values
        for channel, guarantee in zip(channels, block_guarantees, strict=True):
            guarantees[channel] = guarantee
    return ChannelThresholds(values, tuple(guarantees))


@dataclass(frozen=True)
class StoreHealth:
    reachable: bool
    age_seconds: float  # since the store last answered a poll: how stale the cached state may be
    error: str | None  # why the store is unreachable (None while it answers)


@dataclass(frozen=True)
class _Served:
    version: int | None
    table: ScoreTable | None  # None when there is no active version, or it cannot be used


@dataclass(frozen=True)
class _Polled:
    answered_at: float  # time.monotonic() when the last poll the store answered began
    error: str | None  # why the polls since then failed


class CalibrationRegistry:
    """The active version and per-version caches for one model hash, kept fresh by a poller."""

    def __init__(
        self,
        store: CalibrationStore,
        model_hash: str,
        manifest: Manifest,
        poll_seconds: float = POLL_SECONDS,
        store_timeout_seconds: float = STORE_TIMEOUT_SECONDS,
    ) -> None:
        self.store, self.model_hash, self._manifest = store, model_hash, manifest
        self._poll_seconds, self._store_timeout = poll_seconds, store_timeout_seconds
        self.retry_after_s = max(1, math.ceil(poll_seconds))  # a store that returns is seen within one poll
        self._lock = threading.Lock()  # the caches
        self._poll_lock = threading.Lock()  # one poll at a time: the poller's or refresh_now's
        self._incompatibilities: dict[int, str | None] = {}  # versions are immutable: cached forever
        self._strata: dict[int, VersionStrata | None] = {}  # read with the incompatibility, cached too
        self._tables: OrderedDict[int, ScoreTable] = OrderedDict()
        self._served = _Served(None, None)
        self._counter: int | None = None
        self._polled = _Polled(-math.inf, "the store was never polled")
        self._polling_since: float | None = None
        self._stop = threading.Event()
        self._poller: threading.Thread | None = None
        self.thresholds = lru_cache(maxsize=1024)(self._thresholds)
        self.stratified = lru_cache(maxsize=1024)(self._stratified)

    def start(self) -> int | None:
        """Read the active version (StoreError if the store is away), then poll in the background."""
        active = self.refresh_now()
        self._poller = threading.Thread(target=self._poll_forever, name="calibration-poller", daemon=True)
        self._poller.start()
        return active

    def stop(self) -> None:
        self._stop.set()
        if self._poller is not None:
            self._poller.join(timeout=self._store_timeout + 1.0)

    def active_version(self) -> int | None:
        return self._served.version

    def health(self) -> StoreHealth:
        now, polled, since = time.monotonic(), self._polled, self._polling_since
        error = polled.error
        if error is None and since is not None and now - since > 2 * self._store_timeout:  # a hung store
            error = f"the store has not answered a poll for {now - since:.1f} s"
        return StoreHealth(reachable=error is None, age_seconds=now - polled.answered_at, error=error)

    def require_store(self) -> None:
        """503 at once while the polls find the store unreachable (a call would wait for its timeout)."""
        health = self.health()
        if not health.reachable:
            raise StoreUnreachable(
                f"the calibration store is unreachable ({health.error}); calls that need it answer again"
                f" within about {self._poll_seconds:g} s of its return. Predictions keep using the active"
                f" calibration version {self.active_version()} from memory",
                self.retry_after_s,
            )

    def refresh_now(self) -> int | None:
        """Poll the store now (admin calls, after an activation); StoreError if it is away."""
        before = self._polled
        if not self._poll_lock.acquire(timeout=self._store_timeout):
            raise StoreUnavailable(f"the store has not answered a poll for over {self._store_timeout:g} s")
        try:
            polled = self._polled
            if polled is not before and polled.error is not None:  # a poll failed while this one waited
                raise StoreUnavailable(polled.error)
            self._poll(force=True)
        finally:
            self._poll_lock.release()
        return self.active_version()

    def resolve(self, version: int | None) -> int:
        """The version asked for, or the active one, checked usable (404, 409 or 503 if not)."""
        if version is not None:
            self._load_named(version)
            return version
        active = self.active_version()
        if active is None:
            raise Unavailable("no calibration is active for this model: upload and activate one")
        if (reason := self.incompatibility(active)) is not None:
            raise Unavailable(f"the active {reason}")
        return active

    def scores(self, version: int) -> ScoreTable:
        """The version's scores (404 if it does not exist); ``resolve`` checks them usable first."""
        served = self._served
        if version == served.version and served.table is not None:
            return served.table
        with self._lock:
            if version in self._tables:
                self._tables.move_to_end(version)
                return self._tables[version]
        try:
            table = self.store.load_scores(self.model_hash, version)
        except VersionNotFound as error:
            raise NotFound(f"calibration version {version} does not exist for this model") from error
        with self._lock:
            self._tables[version] = table
            while len(self._tables) > CACHED_TABLES:
                self._tables.popitem(last=False)
        return table

    def check_usable(self, version: int) -> None:
        """404 if the version does not exist, 409 if it was scored under other manifest settings."""
        if (reason := self.incompatibility(version)) is not None:
            raise Conflict(reason)

    def incompatibility(self, version: int) -> str | None:
        """Why this version cannot serve the current manifest (None if it can); 404 if it does not exist."""
        with self._lock:
            if version in self._incompatibilities:
                return self._incompatibilities[version]
        try:
            info = self.store.get_version(self.model_hash, version)
        except VersionNotFound as error:
            raise NotFound(f"calibration version {version} does not exist for this model") from error
        reason = version_incompatibility(info, self._manifest)
        strata = None if info.strata is None else VersionStrata.from_dict(info.strata)
        with self._lock:
            self._incompatibilities[version], self._strata[version] = reason, strata
        return reason

    def strata(self, version: int) -> VersionStrata | None:
        """The version's Mondrian strata (None: calibrated without); 404 if it does not exist."""
        self.incompatibility(version)
        with self._lock:
            return self._strata[version]

    def _load_named(self, version: int) -> None:
        """Check and load a version a request names; not tried while the store is unreachable."""
        try:
            health = self.health()
            if not health.reachable and not self._in_memory(version):
                raise StoreUnavailable(health.error or "")
            self.check_usable(version)
            self.scores(version)
        except StoreUnavailable as error:
            raise StoreUnreachable(
                f"calibration version {version} is not in this server's memory and the calibration store"
                f" is unreachable ({error}): retry later, or omit calibration_version to use the active"
                f" version {self.active_version()}, which still answers",
                self.retry_after_s,
            ) from error

    def _in_memory(self, version: int) -> bool:
        with self._lock:
            if version not in self._incompatibilities:
                return False
            unusable = self._incompatibilities[version] is not None
            return unusable or version in self._tables or version == self._served.version

    def _poll_forever(self) -> None:
        while not self._stop.wait(self._poll_seconds):
            try:
                with self._poll_lock:
                    self._poll(force=False)
            except StoreError:  # recorded in health(); the cached state keeps being served
                continue
            except Exception:  # a bug, not an outage: say so, and keep polling
                log.exception("polling the calibration store failed")

    def _poll(self, force: bool) -> None:
        """Read the active version if the change counter moved; a store failure is recorded and raised."""
        began = time.monotonic()
        self._polling_since = began
        try:
            counter = self.store.change_counter()
            if force or counter != self._counter:
                activation = self.store.active_version(self.model_hash)
                self._serve(None if activation is None else activation.version)
                self._counter = counter
        except StoreError as error:
            if self._polled.error is None:
                log.warning(_UNREACHABLE, error, self.active_version())
            self._polled = _Polled(self._polled.answered_at, f"{type(error).__name__}: {error}")
            raise
        finally:
            self._polling_since = None
        if self._polled.error is not None and math.isfinite(self._polled.answered_at):
            log.info("calibration store reachable again after %.1f s", began - self._polled.answered_at)
        self._polled = _Polled(began, None)

    def _serve(self, version: int | None) -> None:
        """Serve ``version`` from now on, its scores loaded first (an unusable one has none)."""
        usable = version is not None and self.incompatibility(version) is None
        self._served = _Served(version, self.scores(version) if usable else None)

    def _stratified(
        self, version: int, kinds: frozenset[str], kind: str, scope: str, epsilon: float, delta: float | None
    ) -> tuple[StratifiedThresholds | None, str | None]:
        """Per-stratum thresholds of ``kinds``, or None and why the version cannot give them."""
        strata = self.strata(version)
        have = frozenset() if strata is None else strata.spec.kinds
        if not kinds <= have:
            return None, (
                f"calibration version {version} has no {describe_kinds(kinds)} strata (it has"
                f" {describe_kinds(have)}): upload a calibration with stratify={describe_kinds(kinds)}"
            )
        if DIFFICULTY in kinds and scope == "object":
            return None, "difficulty strata calibrate each keypoint: use coverage=keypoint, or stratify=group"
        assert strata is not None
        return stratified_thresholds(self.scores(version), strata, kinds, kind, scope, epsilon, delta), None

    def _thresholds(
        self, version: int, kind: str, scope: str, epsilon: float, delta: float | None
    ) -> ChannelThresholds:
        table = self.scores(version)
        return channel_thresholds(table, self._manifest.num_keypoints, kind, scope, epsilon, delta)
