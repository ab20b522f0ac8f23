"""Retained predictions and their field labels, and adaptive (ACI) state: the store side of feedback.

A retained prediction is a row written when a predict answer is kept for feedback: its id, model,
calibration version, camera stream, times, and a JSON ``record`` (whatever the service needs to
judge and recalibrate; the store does not read it). Feedback labels it once: ``label_prediction``
sets its ``labels`` (JSON) in one transaction with the audit entry and the label's verdicts
(``LabelVerdicts``: what live coverage counts of it, read without the record; a row of
calib_verdicts, gone with its prediction), and refuses a second label.
Rows are bounded by age (unlabelled rows past ``expires_at`` are removed) and by count (the oldest
go first). Adaptive state is one JSON row per key, written with compare-and-set on its step count
so that replicas sharing the store never lose an update.
"""

from __future__ import annotations

from collections.abc import Sequence
from dataclasses import dataclass
from datetime import UTC, datetime
from enum import Enum
from typing import Any

from . import codec
from .models import NewAuditEntry


@dataclass(frozen=True)
class RetainedPrediction:
    """One retained predict answer; ``labels`` is None until feedback arrives."""

    id: str
    model_hash: str
    version: int
    stream: str
    created_at: datetime
    expires_at: datetime
    record: dict[str, Any]
    labels: dict[str, Any] | None = None
    labelled_at: datetime | None = None
    labelled_by: str | None = None


@dataclass(frozen=True)
class LabelVerdicts:
    """What live coverage counts of a label, judged once: ``shape``, text that the labels of one
    stream share (kept as given, apart, so that a reader parses each shape once), and ``tally``,
    what is the label's own (JSON)."""

    shape: str
    tally: dict[str, Any]


class LabelOutcome(Enum):
    LABELLED = "labelled"
    ALREADY_LABELLED = "already labelled"
    MISSING = "missing"  # never retained, expired or evicted


@dataclass(frozen=True)
class AdaptiveState:
    """The stored state of one adaptive key; ``steps`` counts the updates applied."""

    key: str
    steps: int
    state: dict[str, Any]


#: ids in one ``IN (...)`` of retained_predictions (SQLite allows 32,766 parameters; PostgreSQL 65,535)
_IDS_PER_QUERY = 500
_RETAINED_COLUMNS = (
    "id, model_hash, version, stream, created_at, expires_at, record, labels, labelled_at, labelled_by"
)


class FeedbackRecords:
    """Mixed into SqlStore: the queries of retained predictions and adaptive state."""

    def retain_predictions(self, batch: Sequence[RetainedPrediction], max_rows: int) -> None:
        """Store ``batch`` in one transaction, then drop expired unlabelled rows and the oldest
        beyond ``max_rows``."""
        if not batch:
            return
        with self._transaction(write=True) as cur:
            for retained in batch:
                cur.execute(
                    f"INSERT INTO calib_retained ({_RETAINED_COLUMNS})"
                    " VALUES (?, ?, ?, ?, ?, ?, ?, NULL, NULL, NULL)",
                    (
                        retained.id,
                        retained.model_hash,
                        retained.version,
                        retained.stream,
                        self._time_to_db(retained.created_at),
                        self._time_to_db(retained.expires_at),
                        codec.encode_json(retained.record),
                    ),
                )
            newest = max(retained.created_at for retained in batch)
            cur.execute(
                "DELETE FROM calib_retained WHERE labels IS NULL AND expires_at < ?",
                (self._time_to_db(newest),),
            )
            cur.execute(  # the oldest beyond max_rows (rows retained in the same instant stay together)
                "DELETE FROM calib_retained WHERE created_at < (SELECT created_at FROM calib_retained"
                " ORDER BY created_at DESC LIMIT 1 OFFSET ?)",
                (max_rows - 1,),
            )

    def retained_prediction(self, prediction_id: str) -> RetainedPrediction | None:
        rows = self._read(f"SELECT {_RETAINED_COLUMNS} FROM calib_retained WHERE id = ?", (prediction_id,))
        return self._retained(rows[0]) if rows else None

    def oldest_retained(self) -> datetime | None:
        """When the oldest kept row was retained (older ids were evicted or expired)."""
        rows = self._read("SELECT MIN(created_at) FROM calib_retained", ())
        return None if rows[0][0] is None else self._time_from_db(rows[0][0])

    def label_prediction(
        self,
        prediction_id: str,
        labels: dict[str, Any],
        who: str,
        at: datetime,
        audit: NewAuditEntry,
        verdicts: LabelVerdicts | None = None,
    ) -> LabelOutcome:
        """Label an unlabelled, unexpired row and append ``audit`` (and store ``verdicts``) in one
        transaction."""
        when = self._time_to_db(at)
        with self._transaction(write=True) as cur:
            cur.execute(
                "UPDATE calib_retained SET labels = ?, labelled_at = ?, labelled_by = ?"
                " WHERE id = ? AND labels IS NULL AND expires_at >= ? RETURNING id",
                (codec.encode_json(labels), when, who, prediction_id, when),
            )
            if cur.fetchone() is not None:
                if verdicts is not None:
                    cur.execute(
                        "INSERT INTO calib_verdicts (id, shape, tally) VALUES (?, ?, ?)",
                        (prediction_id, verdicts.shape, codec.encode_json(verdicts.tally)),
                    )
                self._insert_audit(cur, audit)
                return LabelOutcome.LABELLED
            cur.execute("SELECT labels FROM calib_retained WHERE id = ?", (prediction_id,))
            row = cur.fetchone()
        if row is not None and row[0] is not None:
            return LabelOutcome.ALREADY_LABELLED
        return LabelOutcome.MISSING

    def labelled_predictions(self, model_hash: str, limit: int) -> list[RetainedPrediction]:
        """The newest ``limit`` labelled rows of a model, in the order they were labelled."""
        rows = self._read(
            f"SELECT {_RETAINED_COLUMNS} FROM calib_retained WHERE model_hash = ? AND labels IS NOT NULL"
            " ORDER BY labelled_at DESC, id DESC LIMIT ?",
            (model_hash, limit),
        )
        return [self._retained(row) for row in reversed(rows)]

    def labelled_since(self, model_hash: str, since: datetime | None) -> list[tuple[str, datetime]]:
        """(id, labelled_at) of a model's rows labelled at or after ``since`` (None: all kept), in
        label order: the cheap half of reading new labels (the records are fetched by id)."""
        rows = self._read(
            "SELECT id, labelled_at FROM calib_retained WHERE model_hash = ? AND labelled_at >= ?"
            " ORDER BY labelled_at, id",
            (model_hash, self._time_to_db(since or datetime.fromtimestamp(0, UTC))),
        )
        return [(row[0], self._time_from_db(row[1])) for row in rows]

    def retained_predictions(self, ids: Sequence[str]) -> list[RetainedPrediction]:
        """The kept rows of ``ids`` (those evicted since are missing), in no particular order."""
        rows = self._rows_of(f"SELECT {_RETAINED_COLUMNS} FROM calib_retained", ids)
        return [self._retained(row) for row in rows]

    def label_verdicts(self, ids: Sequence[str]) -> dict[str, LabelVerdicts]:
        """id -> the stored verdicts of those of ``ids`` that have them (rows labelled before
        schema 10, or evicted since, have none)."""
        rows = self._rows_of("SELECT id, shape, tally FROM calib_verdicts", ids)
        return {row[0]: LabelVerdicts(row[1], codec.decode_json(row[2])) for row in rows}

    def _rows_of(self, select: str, ids: Sequence[str]) -> list[Any]:
        """The rows of ``select`` whose id is one of ``ids``, a query per ``_IDS_PER_QUERY``."""
        rows: list[Any] = []
        for start in range(0, len(ids), _IDS_PER_QUERY):
            chunk = tuple(ids[start : start + _IDS_PER_QUERY])
            rows.extend(self._read(f"{select} WHERE id IN ({', '.join('?' * len(chunk))})", chunk))
        return rows

    def adaptive_state(self, key: str) -> AdaptiveState | None:
        rows = self._read("SELECT key, steps, state FROM calib_adaptive WHERE key = ?", (key,))
        return AdaptiveState(rows[0][0], int(rows[0][1]), codec.decode_json(rows[0][2])) if rows else None

    def save_adaptive_state(self, key: str, steps_before: int, state: AdaptiveState) -> bool:
        """Write ``state`` if the stored one still has ``steps_before`` steps (0: none stored);
        False when another writer got there first (read again and retry)."""
        encoded = codec.encode_json(state.state)
        with self._transaction(write=True) as cur:
            if steps_before == 0:
                cur.execute(
                    "INSERT INTO calib_adaptive (key, steps, state) VALUES (?, ?, ?)"
                    " ON CONFLICT (key) DO NOTHING RETURNING key",
                    (key, state.steps, encoded),
                )
            else:
                cur.execute(
                    "UPDATE calib_adaptive SET steps = ?, state = ?"
                    " WHERE key = ? AND steps = ? RETURNING key",
                    (state.steps, encoded, key, steps_before),
                )
            return cur.fetchone() is not None

    def _retained(self, row: Any) -> RetainedPrediction:
        at = self._time_from_db
        return RetainedPrediction(
            id=row[0],
            model_hash=row[1],
            version=int(row[2]),
            stream=row[3],
            created_at=at(row[4]),
            expires_at=at(row[5]),
            record=codec.decode_json(row[6]),
            labels=None if row[7] is None else codec.decode_json(row[7]),
            labelled_at=None if row[8] is None else at(row[8]),
            labelled_by=row[9],
        )


def feedback_tables(timestamp: str) -> tuple[str, ...]:
    """Migration: retained predictions (mutable once: their labels) and adaptive state."""
    return (
        f"""CREATE TABLE calib_retained (
            id TEXT PRIMARY KEY,
            model_hash TEXT NOT NULL,
            version INTEGER NOT NULL,
            stream TEXT NOT NULL,
            created_at {timestamp} NOT NULL,
            expires_at {timestamp} NOT NULL,
            record TEXT NOT NULL,
            labels TEXT,
            labelled_at {timestamp},
            labelled_by TEXT
        )""",
        "CREATE INDEX calib_retained_by_created ON calib_retained (created_at)",
        "CREATE INDEX calib_retained_by_label ON calib_retained (model_hash, labelled_at)",
        """CREATE TABLE calib_adaptive (
            key TEXT PRIMARY KEY,
            steps BIGINT NOT NULL CHECK (steps >= 0),
            state TEXT NOT NULL
        )""",
    )


FEEDBACK_TABLES = "retained predictions, their field labels, adaptive conformal state"

#: Migration: the verdicts of each label (what live coverage counts), apart from the big records
#: so that reading them reads none of a record's pages; removed with their prediction
VERDICTS_TABLE = "the verdicts of field labels, for live coverage"
VERDICTS_STATEMENTS = (
    """CREATE TABLE calib_verdicts (
        id TEXT PRIMARY KEY REFERENCES calib_retained (id) ON DELETE CASCADE,
        shape TEXT NOT NULL,
        tally TEXT NOT NULL
    )""",
)
