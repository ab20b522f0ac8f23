"""Keeping a predict answer for feedback: per row what scores a true point (heatmap statistics, the
image -> heatmap affine) and the set served; per request its version, query, image, stream, client, look.
"""

from __future__ import annotations

import logging
import math
import random
import secrets
import threading
import time
from collections import OrderedDict
from dataclasses import dataclass
from datetime import UTC, datetime, timedelta
from typing import Any

import numpy as np

from calibration_store import RetainedPrediction, StoreError
from service.calibration.stratification import Stratum
from service.conformal import CoverageGuarantee
from service.monitoring.looks import Frame, LookTracker

log = logging.getLogger(__name__)
#: how often a write the store refused is tried again
RETRY_S = 1.0
#: how long the writer lets answers gather before a write (their requests finish first)
GATHER_S = 0.05
#: camera streams whose looks are followed (the least recently served beyond it start afresh)
LOOK_STREAMS = 1024
#: prediction ids: "p" + creation time (ms since the epoch, 12 hex digits) + 20 random hex digits
ID_PREFIX = "p"
_TIME_DIGITS = 12


@dataclass(frozen=True)
class RetentionRules:
    """CKS_FEEDBACK_RETAIN_SHARE, CKS_FEEDBACK_MAX_AGE_SECONDS, CKS_FEEDBACK_MAX_RETAINED."""

    share: float
    max_age: timedelta
    max_rows: int


@dataclass(frozen=True)
class ServedRequest:
    """What a retained answer was asked and served, in plain values (from the predict use case)."""

    query: dict[str, Any]  # nonconformity, coverage, epsilon, delta
    instances: list[dict[str, Any]]  # object, bbox, group, affine
    rows: list[dict[str, Any]]
    heatmap_shape: tuple[int, int]
    width: int
    height: int
    adaptive: dict[str, Any] | None = None


class Retention:
    """Decides which answers are kept and writes them from a background thread (answers never wait)."""

    def __init__(self, store: Any, model_hash: str, rules: RetentionRules, seed: int | None = None) -> None:
        self._store, self._model_hash, self.rules = store, model_hash, rules
        self._random = random.Random(seed)
        self._pending: list[RetainedPrediction] = []
        self._changed = threading.Condition()
        self._writing = 0  # rows taken by the writer, not yet committed (-1: gathering them)
        self._closed = False
        self._looks: OrderedDict[str, tuple[LookTracker, str]] = OrderedDict()
        self._looks_lock = threading.Lock()
        self._writer = threading.Thread(target=self._write_loop, name="retention-writer", daemon=True)
        self._writer.start()

    def wanted(self, requested: bool) -> bool:
        """Asked for (``retain: true``), or drawn with probability CKS_FEEDBACK_RETAIN_SHARE."""
        return requested or (self.rules.share > 0 and self._random.random() < self.rules.share)

    def retain(
        self, version: int, served: ServedRequest, image_sha256: str, stream: str | None, client: str
    ) -> str:
        now = datetime.now(UTC)
        prediction_id = new_prediction_id(now)
        record = {
            "query": served.query,
            "image": {"sha256": image_sha256, "width": served.width, "height": served.height},
            "heatmap_shape": list(served.heatmap_shape),
            "client": client,
            "instances": served.instances,
            "rows": served.rows,
            "adaptive": served.adaptive,
            "look": self._look(stream or f"client:{client}", served.instances, prediction_id),
        }
        retained = RetainedPrediction(
            prediction_id, self._model_hash, version, stream or "", now, now + self.rules.max_age, record
        )
        with self._changed:
            self._pending.append(retained)
            self._changed.notify_all()
        return prediction_id

    def _look(self, stream: str, instances: list[dict[str, Any]], prediction_id: str) -> str:
        """The look this answer belongs to, named by its first retained frame."""
        frame = Frame(tuple(i["object"] for i in instances), np.array([i["bbox"] for i in instances]))
        with self._looks_lock:
            tracker, look = self._looks.pop(stream, (LookTracker(), prediction_id))
            if tracker.is_new_look(frame):
                look = prediction_id
            self._looks[stream] = (tracker, look)
            if len(self._looks) > LOOK_STREAMS:
                self._looks.popitem(last=False)
        return look

    def flush(self, timeout_s: float = 10.0) -> None:
        """Wait until every answer queued so far is in the store (or ``timeout_s`` has passed)."""
        with self._changed:
            self._changed.wait_for(lambda: not self._pending and not self._writing, timeout_s)

    def close(self, timeout_s: float = 2.0) -> None:
        """Write what is queued (``timeout_s`` at most), then stop the writer."""
        self.flush(timeout_s)
        with self._changed:
            self._closed = True
            lost = len(self._pending) + max(self._writing, 0)
            self._changed.notify_all()
        if lost:
            log.warning(
                "%d retained predictions were not stored before shutdown: their feedback gets 404", lost
            )

    def _write_loop(self) -> None:
        while True:
            with self._changed:
                self._changed.wait_for(lambda: self._pending or self._closed)
                if self._closed and not self._pending:
                    return
                self._writing = -1  # gathering: flush waits for it too
            time.sleep(GATHER_S)
            with self._changed:
                batch, self._pending = self._pending, []
                self._writing = len(batch)
            while True:
                try:
                    self._store.retain_predictions(batch, self.rules.max_rows)
                    break
                except StoreError:
                    if self._closed:  # shutting down: close() has logged what is lost
                        break
                    log.warning(
                        "retained predictions not stored yet (%d); retrying", len(batch), exc_info=True
                    )
                    time.sleep(RETRY_S)
            with self._changed:
                self._writing = 0
                self._changed.notify_all()


def new_prediction_id(at: datetime) -> str:
    milliseconds = int(at.timestamp() * 1000)
    return f"{ID_PREFIX}{milliseconds:0{_TIME_DIGITS}x}{secrets.token_hex(10)}"


def retained_at(prediction_id: str) -> datetime | None:
    """When a well-formed id was made (None: not an id this service makes)."""
    if not prediction_id.startswith(ID_PREFIX) or len(prediction_id) != len(ID_PREFIX) + _TIME_DIGITS + 20:
        return None
    try:
        int(prediction_id[len(ID_PREFIX) :], 16)
        milliseconds = int(prediction_id[len(ID_PREFIX) : len(ID_PREFIX) + _TIME_DIGITS], 16)
        return datetime.fromtimestamp(milliseconds / 1000, UTC)
    except (ValueError, OverflowError, OSError):  # not hex, or a time no clock reaches
        return None


def guarantee_values(guarantee: CoverageGuarantee) -> dict[str, Any]:
    return {"n": guarantee.n, "t": guarantee.t, "epsilon": guarantee.epsilon, "delta": guarantee.delta}


def stratum_name(stratum: Stratum | None) -> str | None:
    """The Mondrian stratum that answered a row, as live coverage names it (None: not stratified)."""
    if stratum is None:
        return None
    if stratum.kinds == "pooled":
        return "pooled"
    parts = [] if stratum.group is None else [f"group {stratum.group}"]
    parts += [] if stratum.bin is None else [f"difficulty bin {stratum.bin}"]
    return ", ".join(parts) or "all instances"


def finite_or_none(value: float) -> float | None:
    """JSON keeps finite numbers only: an unbounded set's threshold is stored as null."""
    return value if math.isfinite(value) else None
