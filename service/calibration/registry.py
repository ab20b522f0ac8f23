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
from service.conformal import calibrate_threshold
from service.conformal.guarantees import Guarantee
from service.errors import NotFound, Unavailable


@dataclass(frozen=True)
class ChannelThresholds:
    """One threshold and guarantee per manifest keypoint channel (``inf`` = unbounded)."""

    values: np.ndarray  # (K,) float64
    guarantees: tuple[Guarantee, ...]


def calibration_scores(table: ScoreTable, kind: str, scope: str) -> dict[tuple[int, ...], np.ndarray]:
    """Group calibration scores by the channels one threshold serves.

    ``keypoint`` scope: one group per keypoint channel, its labeled instances' scores.
    ``object`` scope: one group per object, the max score over each fully labeled instance.
    """
    groups: dict[tuple[int, ...], np.ndarray] = {}
    for block in table.objects:
        matrix = block.scores[kind]
        channels = tuple(int(c) for c in block.keypoint_ids)
        if scope == "object":
            complete = ~np.isnan(matrix).any(axis=1)
            groups[channels] = (
                matrix[complete].max(axis=1, initial=-np.inf) if complete.any() else np.empty(0)
            )
        else:
            for column, channel in enumerate(channels):
                scores = matrix[:, column]
                groups[(channel,)] = scores[~np.isnan(scores)]
    return groups


class CalibrationRegistry:
    """Active-version tracking plus per-version caches for one model hash."""

    def __init__(
        self, store: CalibrationStore, model_hash: str, num_keypoints: int, poll_seconds: float
    ) -> None:
        self.store = store
        self.model_hash = model_hash
        self._num_keypoints = num_keypoints
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
        """The version a request asked for, or the active one; 404/503 when there is none."""
        if version is None:
            active = self.active_version()
            if active is None:
                raise Unavailable("no calibration is active for this model: upload and activate one")
            return active
        self.scores(version)
        return version

    def scores(self, version: int) -> ScoreTable:
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

    def _refresh(self) -> None:
        counter = self.store.change_counter()
        if counter != self._counter:
            activation = self.store.active_version(self.model_hash)
            self._active = activation.version if activation else None
            self._counter = counter

    def _thresholds(
        self, version: int, kind: str, scope: str, epsilon: float, delta: float | None
    ) -> ChannelThresholds:
        groups = calibration_scores(self.scores(version), kind, scope)
        values = np.full(self._num_keypoints, np.inf)
        guarantees: list[Guarantee | None] = [None] * self._num_keypoints
        for channels, scores in groups.items():
            threshold, guarantee = calibrate_threshold(scores, epsilon, delta)
            for channel in channels:
                values[channel], guarantees[channel] = threshold, guarantee
        empty, _ = None, None
        for channel, guarantee in enumerate(guarantees):
            if guarantee is None:
                if empty is None:
                    _, empty = calibrate_threshold(np.empty(0), epsilon, delta)
                guarantees[channel] = empty
        return ChannelThresholds(values, tuple(guarantees))
