"""The served model's calibrations: which version is active, and cached thresholds per version.

Versions are immutable, so scores and thresholds are cached by version number and never
invalidated; only the *active* pointer changes, and it is re-read at most once per
``poll_seconds`` (when the store's change counter moves), which is how replicas see each
other's activations.
"""

from __future__ import annotations

import threading
import time
from collections import OrderedDict
from dataclasses import dataclass
from functools import lru_cache

import numpy as np

from calibration_store import CalibrationStore, ScoreTable, VersionNotFound
from service.calibration.compatibility import version_incompatibility
from service.conformal import (
    CoverageGuarantee,
    calibrate,
    calibrate_columns,
    coverage_guarantee,
    object_scores,
)
from service.detector.manifest import Manifest
from service.errors import Conflict, NotFound, Unavailable


@dataclass(frozen=True)
class ChannelThresholds:
    """One threshold and guarantee per manifest keypoint channel (``inf`` = unbounded)."""

    values: np.ndarray  # (K,) float64
    guarantees: tuple[CoverageGuarantee, ...]


def channel_thresholds(
    table: ScoreTable, num_keypoints: int, kind: str, scope: str, epsilon: float, delta: float | None
) -> ChannelThresholds:
    """Thresholds for every keypoint channel; a channel without calibration data is unbounded.

    ``keypoint`` scope calibrates each keypoint column on its labeled instances; ``object``
    scope calibrates the max over each fully labeled instance, one threshold per object.
    """
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


class CalibrationRegistry:
    """Active-version tracking plus per-version caches for one model hash."""

    def __init__(
        self,
        store: CalibrationStore,
        model_hash: str,
        manifest: Manifest,
        poll_seconds: float,
    ) -> None:
        self.store = store
        self.model_hash = model_hash
        self._manifest = manifest
        self._incompatibilities: dict[int, str | None] = {}  # versions are immutable: cached forever
        self._poll_seconds = poll_seconds
        self._lock = threading.Lock()
        self._checked_at = -np.inf
        self._counter: int | None = None
        self._active: int | None = None
        self._tables: OrderedDict[int, ScoreTable] = OrderedDict()
        self.thresholds = lru_cache(maxsize=1024)(self._thresholds)

    def active_version(self) -> int | None:
        """The active version number, refreshed from the store at most once per poll interval."""
        now = time.monotonic()
        with self._lock:
            if now - self._checked_at >= self._poll_seconds:
                self._refresh()
                self._checked_at = now
            return self._active

    def refresh_now(self) -> int | None:
        with self._lock:
            self._counter = None
            self._refresh()
            self._checked_at = time.monotonic()
            return self._active

    def resolve(self, version: int | None) -> int:
        """The version a request asked for, or the active one, checked usable for this manifest.

        A named version: 404 if missing, 409 if scored under other manifest settings. The
        active one: 503 if there is none or it is unusable (the caller did nothing wrong).
        """
        if version is not None:
            self.check_usable(version)
            return version
        active = self.active_version()
        if active is None:
            raise Unavailable("no calibration is active for this model: upload and activate one")
        reason = self.incompatibility(active)
        if reason is not None:
            raise Unavailable(f"the active {reason}")
        return active

    def scores(self, version: int) -> ScoreTable:
        """The version's scores (404 if it does not exist); ``resolve`` checks them usable first."""
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
            while len(self._tables) > 8:
                self._tables.popitem(last=False)
        return table

    def check_usable(self, version: int) -> None:
        """404 if the version does not exist, 409 if it was scored under other manifest settings."""
        reason = self.incompatibility(version)
        if reason is not None:
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
        with self._lock:
            self._incompatibilities[version] = reason
        return reason

    def _refresh(self) -> None:
        counter = self.store.change_counter()
        if counter != self._counter:
            activation = self.store.active_version(self.model_hash)
            self._active = activation.version if activation else None
            self._counter = counter

    def _thresholds(
        self, version: int, kind: str, scope: str, epsilon: float, delta: float | None
    ) -> ChannelThresholds:
        table = self.scores(version)
        return channel_thresholds(table, self._manifest.num_keypoints, kind, scope, epsilon, delta)
