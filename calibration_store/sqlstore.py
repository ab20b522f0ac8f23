"""Store logic shared by the SQL backends: one set of queries, '?' placeholders.

A backend supplies `_transaction(write)` (a context manager yielding a cursor, committing
on success and rolling back on error; write transactions are serialized per database on
SQLite and per model row on PostgreSQL), plus the timestamp conversions.
"""

from __future__ import annotations

from abc import abstractmethod
from collections.abc import Iterator, Sequence
from contextlib import AbstractContextManager
from dataclasses import dataclass, replace
from datetime import UTC, datetime, timedelta
from typing import Any, ClassVar, Protocol

from . import codec
from .base import JOB_MAX_AGE, KEEP_JOBS, CalibrationStore
from .errors import DuplicateVersion, JobExists, JobFinished, JobNotFound, VersionNotFound
from .feedback_records import FeedbackRecords
from .models import (
    FINAL_JOB_STATES,
    Activation,
    ActivationIntent,
    AuditEntry,
    CoverageAudit,
    JobCompletion,
    JobRecord,
    MonitorShare,
    NewAuditEntry,
    NewCoverageAudit,
    NewVersion,
    ObjectScores,
    ScoreTable,
    SourceBatch,
    VersionInfo,
    check_job_field,
    check_model_hash,
    check_number,
    is_job_id,
)


class Cursor(Protocol):
    def execute(self, sql: str, params: Sequence[Any] = ...) -> Any: ...
    def fetchone(self) -> Any: ...
    def fetchall(self) -> list[Any]: ...


@dataclass(frozen=True)
class EncodedBlock:
    """One ObjectScores turned into storable values (done before the transaction)."""

    position: int
    object_name: str
    n_instances: int
    keypoint_ids: bytes
    instance_refs: str
    arrays: tuple[tuple[str, int, int, bytes], ...]
    image_hashes: bytes | None
    instance_hashes: bytes | None
    features: tuple[tuple[str, int, int, bytes], ...]
    groups: str | None


def encode_block(position: int, block: ObjectScores) -> EncodedBlock:
    n, k = block.n_instances, block.keypoint_ids.size
    arrays = tuple((fn, n, k, codec.encode_matrix(block.scores[fn])) for fn in block.functions)
    features = tuple(
        (name, n, k, codec.encode_matrix(block.features[name])) for name in sorted(block.features)
    )
    return EncodedBlock(
        position=position,
        object_name=block.object_name,
        n_instances=n,
        keypoint_ids=codec.encode_ids(block.keypoint_ids),
        instance_refs=codec.encode_refs(block.instance_refs),
        arrays=arrays,
        image_hashes=codec.encode_digests(block.image_hashes),
        instance_hashes=codec.encode_digests(block.instance_hashes),
        features=features,
        groups=codec.encode_refs(block.groups) if block.has_groups else None,
    )


_VERSION_COLUMNS = (
    "model_hash, number, model_name, normalization, source_batches, author, note,"
    " parent_number, created_at, n_instances, object_counts, functions, strata"
)
_STRATA_COLUMN = ", strata"  # written only for a version that has strata
_ACTIVATION_COLUMNS = "seq, model_hash, number, activated_at, who, reason"
_JOB_COLUMNS = (
    "id, kind, owner, created_at, heartbeat_at, state, done, total, errors, result, finished_at, version"
)
_AUDIT_COLUMNS = (
    "seq, at, model_hash, who, action, outcome, version, previous_version, reason, client, details"
)
_COVERAGE_AUDIT_COLUMNS = "id, model_hash, version, created_at, who, batch_sha256, n_instances, report"
_FINAL_STATES_SQL = ", ".join(f"'{state}'" for state in FINAL_JOB_STATES)


def now_utc() -> datetime:
    return datetime.now(UTC)


class SqlStore(FeedbackRecords, CalibrationStore):
    """CalibrationStore over a SQL database (and the feedback records); subclasses provide connections."""

    #: appended to the SELECT that locks a model row before activating
    lock_clause: ClassVar[str] = ""

    @abstractmethod
    def _transaction(self, write: bool) -> AbstractContextManager[Cursor]:
        """Cursor inside a transaction (write=True: exclusive for writers)."""

    @abstractmethod
    def _time_to_db(self, value: datetime) -> Any: ...

    @abstractmethod
    def _time_from_db(self, value: Any) -> datetime: ...

    # -- writing ---------------------------------------------------------------

    def create_version(
        self,
        new: NewVersion,
        scores: ScoreTable,
        *,
        activation: ActivationIntent | None = None,
        job: JobCompletion | None = None,
        audit: Sequence[NewAuditEntry] = (),
    ) -> VersionInfo:
        blocks = _encoded_blocks(new, scores, "create_version")
        _check_types(activation, ActivationIntent, "activation")
        _check_types(job, JobCompletion, "job")
        entries = _audit_entries(audit)
        with self._transaction(write=True) as cur:
            number = self._next_number(cur, new.model_hash)  # writers of one model wait here
            if new.parent_version is not None:
                self._version_id(cur, new.model_hash, new.parent_version)
            if new.content_key is not None:
                self._refuse_same_content(cur, new.model_hash, new.content_key)
            self._write_version(cur, new, number, scores, blocks)
            if activation is not None:
                self._insert_activation(cur, new.model_hash, number, activation.who, activation.reason)
            if job is not None:
                self._complete_job(cur, job, number)
            for entry in entries:
                self._insert_audit(cur, replace(entry, version=number) if entry.version is None else entry)
        return self.get_version(new.model_hash, number)

    def _refuse_same_content(self, cur: Cursor, model_hash: str, content_key: str) -> None:
        """DuplicateVersion when a version of the model has this content key. Writers of a model
        are serialized before this read (its counter row), so it sees every committed version; the
        unique index calib_versions_by_content holds the rule should a writer skip the read."""
        cur.execute(
            "SELECT number FROM calib_versions WHERE model_hash = ? AND content_key = ?",
            (model_hash, content_key),
        )
        row = cur.fetchone()
        if row is not None:
            raise DuplicateVersion(model_hash, int(row[0]))

    def _complete_job(self, cur: Cursor, job: JobCompletion, number: int) -> None:
        """Mark the job succeeded with the version; refuse (rolling back) a finished or missing job."""
        self._mark_succeeded(cur, job.job_id, {**job.result, "version": number}, number)

    def _mark_succeeded(self, cur: Cursor, job_id: str, result: dict, version: int | None) -> None:
        now = self._time_to_db(now_utc())
        cur.execute(
            "UPDATE calib_jobs SET state = 'succeeded', done = total, result = ?, version = ?,"
            " finished_at = ?, heartbeat_at = ?"
            f" WHERE id = ? AND state NOT IN ({_FINAL_STATES_SQL}) RETURNING id",
            (codec.encode_json(result), version, now, now, job_id),
        )
        if cur.fetchone() is None:
            self._raise_job_unchangeable(cur, job_id)

    def _raise_job_unchangeable(self, cur: Cursor, job_id: str) -> None:
        cur.execute("SELECT state FROM calib_jobs WHERE id = ?", (job_id,))
        row = cur.fetchone()
        if row is None:
            raise JobNotFound(job_id)
        raise JobFinished(job_id, row[0])

    def create_first_version(
        self, new: NewVersion, scores: ScoreTable, who: str, reason: str = ""
    ) -> VersionInfo | None:
        blocks = _encoded_blocks(new, scores, "create_first_version")
        if new.parent_version is not None:
            raise ValueError("a first version has no parent_version")
        _check_activation_text(who, reason)
        try:
            with self._transaction(write=True) as cur:
                # The counter row's lock orders concurrent callers: only one sees number 1.
                if self._next_number(cur, new.model_hash) != 1:
                    raise _NotFirst
                self._write_version(cur, new, 1, scores, blocks)
                self._insert_activation(cur, new.model_hash, 1, who, reason)
        except _NotFirst:
            return None  # rolled back: the counter bump too
        return self.get_version(new.model_hash, 1)

    def _write_version(
        self, cur: Cursor, new: NewVersion, number: int, scores: ScoreTable, blocks: list[EncodedBlock]
    ) -> None:
        version_id = self._insert_version(cur, new, number, now_utc(), scores)
        for block in blocks:
            self._insert_block(cur, version_id, block)
        self._bump_counter(cur)

    def _next_number(self, cur: Cursor, model_hash: str) -> int:
        cur.execute(
            "INSERT INTO calib_models (model_hash, last_number) VALUES (?, 1)"
            " ON CONFLICT (model_hash) DO UPDATE"
            " SET last_number = calib_models.last_number + 1 RETURNING last_number",
            (model_hash,),
        )
        return int(cur.fetchone()[0])

    def _insert_version(
        self, cur: Cursor, new: NewVersion, number: int, created_at: datetime, scores: ScoreTable
    ) -> int:
        # optional columns are named only when given (a database of an older schema lacks them)
        optional = {"strata": None if new.strata is None else codec.encode_json(new.strata)}
        optional["content_key"] = new.content_key
        given = {column: value for column, value in optional.items() if value is not None}
        columns = _VERSION_COLUMNS.removesuffix(_STRATA_COLUMN) + "".join(f", {c}" for c in given)
        marks = ", ".join("?" * (12 + len(given)))
        cur.execute(
            f"INSERT INTO calib_versions ({columns}) VALUES ({marks}) RETURNING id",
            (
                new.model_hash,
                number,
                new.model_name,
                codec.encode_json(new.normalization),
                codec.encode_json([b.as_dict() for b in new.source_batches]),
                new.author,
                new.note,
                new.parent_version,
                self._time_to_db(created_at),
                scores.n_instances,
                codec.encode_json(scores.object_counts()),
                codec.encode_json(list(scores.functions)),
                *given.values(),
            ),
        )
        return int(cur.fetchone()[0])

    def _insert_block(self, cur: Cursor, version_id: int, block: EncodedBlock) -> None:
        cur.execute(
            "INSERT INTO calib_score_objects (version_id, position, object_name, n_instances,"
            " keypoint_ids, instance_refs, image_hashes, instance_hashes, groups)"
            " VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?)",
            (
                version_id,
                block.position,
                block.object_name,
                block.n_instances,
                block.keypoint_ids,
                block.instance_refs,
                block.image_hashes,
                block.instance_hashes,
                block.groups,
            ),
        )
        for table, column, arrays in (
            ("calib_score_arrays", "function", block.arrays),
            ("calib_feature_arrays", "feature", block.features),
        ):
            for name, rows, cols, data in arrays:
                cur.execute(
                    f"INSERT INTO {table} (version_id, object_name, {column}, n_rows,"
                    " n_cols, data) VALUES (?, ?, ?, ?, ?, ?)",
                    (version_id, block.object_name, name, rows, cols, data),
                )

    def _bump_counter(self, cur: Cursor) -> None:
        cur.execute("UPDATE calib_change_counter SET value = value + 1 WHERE id = 1")

    def activate(
        self, model_hash: str, number: int, who: str, reason: str = "", audit: Sequence[NewAuditEntry] = ()
    ) -> Activation:
        check_model_hash(model_hash)
        check_number(number)
        _check_activation_text(who, reason)
        entries = _audit_entries(audit)
        with self._transaction(write=True) as cur:
            cur.execute(
                f"SELECT last_number FROM calib_models WHERE model_hash = ?{self.lock_clause}",
                (model_hash,),
            )
            if cur.fetchone() is None:
                raise VersionNotFound(model_hash, number)
            self._version_id(cur, model_hash, number)
            activation = self._insert_activation(cur, model_hash, number, who, reason)
            self._bump_counter(cur)
            for entry in entries:
                self._insert_audit(cur, entry)
        return activation

    # -- audit -----------------------------------------------------------------

    def append_audit(self, entry: NewAuditEntry) -> AuditEntry:
        (entry,) = _audit_entries((entry,))
        with self._transaction(write=True) as cur:
            return self._insert_audit(cur, entry)

    def _insert_audit(self, cur: Cursor, entry: NewAuditEntry) -> AuditEntry:
        cur.execute(
            "INSERT INTO calib_audit (at, model_hash, who, action, outcome, version, previous_version,"
            f" reason, client, details) VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?) RETURNING {_AUDIT_COLUMNS}",
            (
                self._time_to_db(now_utc()),
                entry.model_hash,
                entry.who,
                entry.action,
                entry.outcome,
                entry.version,
                entry.previous_version,
                entry.reason,
                entry.client,
                codec.encode_json(entry.details),
            ),
        )
        return self._audit(cur.fetchone())

    def put_monitor_share(self, model_hash: str, kind: str, replica: str, payload: bytes) -> None:
        with self._transaction(write=True) as cur:
            cur.execute(
                "INSERT INTO calib_monitor_shares (model_hash, kind, replica, updated_at, payload)"
                " VALUES (?, ?, ?, ?, ?) ON CONFLICT (model_hash, kind, replica)"
                " DO UPDATE SET updated_at = excluded.updated_at, payload = excluded.payload",
                (model_hash, kind, replica, self._time_to_db(now_utc()), payload),
            )

    def monitor_shares(self, model_hash: str, kind: str) -> list[MonitorShare]:
        with self._transaction(write=False) as cur:
            cur.execute(
                "SELECT replica, updated_at, payload FROM calib_monitor_shares"
                " WHERE model_hash = ? AND kind = ?",
                (model_hash, kind),
            )
            rows = cur.fetchall()
        shares = [MonitorShare(r[0], self._time_from_db(r[1]), bytes(r[2])) for r in rows]
        return sorted(shares, key=lambda share: share.updated_at)

    def forget_monitor_share(self, model_hash: str, kind: str, replica: str) -> bool:
        with self._transaction(write=True) as cur:
            cur.execute(
                "DELETE FROM calib_monitor_shares WHERE model_hash = ? AND kind = ? AND replica = ?"
                " RETURNING replica",
                (model_hash, kind, replica),
            )
            return bool(cur.fetchall())

    def audit_log(self, model_hash: str, before: int | None = None, limit: int = 100) -> list[AuditEntry]:
        rows = self._newest_first(_AUDIT_COLUMNS, "calib_audit", "seq", model_hash, before, limit)
        return [self._audit(row) for row in rows]

    def _newest_first(
        self, columns: str, table: str, key: str, model_hash: str, before: int | None, limit: int
    ) -> list[tuple]:
        """One page of a model's rows of an append-only table, newest first, below ``before``."""
        check_model_hash(model_hash)
        limit = check_number(limit, "audit page size")
        bound = _MAX_SEQ if before is None else check_number(before, "audit cursor")
        return self._read(
            f"SELECT {columns} FROM {table} WHERE model_hash = ? AND {key} < ? ORDER BY {key} DESC LIMIT ?",
            (model_hash, bound, limit),
        )

    # -- coverage audits ---------------------------------------------------------

    def create_coverage_audit(self, new: NewCoverageAudit, job: JobCompletion | None = None) -> CoverageAudit:
        if not isinstance(new, NewCoverageAudit):
            raise TypeError("create_coverage_audit takes a NewCoverageAudit")
        _check_types(job, JobCompletion, "job")
        with self._transaction(write=True) as cur:
            self._version_id(cur, new.model_hash, new.version)
            cur.execute(
                "INSERT INTO calib_coverage_audits (model_hash, version, created_at, who, batch_sha256,"
                f" n_instances, report) VALUES (?, ?, ?, ?, ?, ?, ?) RETURNING {_COVERAGE_AUDIT_COLUMNS}",
                (
                    new.model_hash,
                    new.version,
                    self._time_to_db(now_utc()),
                    new.who,
                    new.batch_sha256,
                    new.n_instances,
                    codec.encode_json(dict(new.report)),
                ),
            )
            audit = self._coverage_audit(cur.fetchone())
            if job is not None:
                self._mark_succeeded(cur, job.job_id, {**job.result, "audit": audit.id}, None)
        return audit

    def coverage_audits(
        self, model_hash: str, before: int | None = None, limit: int = 100
    ) -> list[CoverageAudit]:
        table = "calib_coverage_audits"
        rows = self._newest_first(_COVERAGE_AUDIT_COLUMNS, table, "id", model_hash, before, limit)
        return [self._coverage_audit(row) for row in rows]

    def coverage_audit(self, model_hash: str, audit_id: int) -> CoverageAudit | None:
        check_model_hash(model_hash)
        check_number(audit_id, "audit id")
        if audit_id > _MAX_SEQ:
            return None
        rows = self._read(
            f"SELECT {_COVERAGE_AUDIT_COLUMNS} FROM calib_coverage_audits WHERE model_hash = ? AND id = ?",
            (model_hash, audit_id),
        )
        return self._coverage_audit(rows[0]) if rows else None

    def _insert_activation(
        self, cur: Cursor, model_hash: str, number: int, who: str, reason: str
    ) -> Activation:
        cur.execute(
            "INSERT INTO calib_activations (model_hash, number, activated_at, who, reason)"
            f" VALUES (?, ?, ?, ?, ?) RETURNING {_ACTIVATION_COLUMNS}",
            (model_hash, number, self._time_to_db(now_utc()), who, reason),
        )
        return self._activation(cur.fetchone())

    # -- reading ---------------------------------------------------------------

    def _version_id(self, cur: Cursor, model_hash: str, number: int) -> int:
        cur.execute(
            "SELECT id FROM calib_versions WHERE model_hash = ? AND number = ?",
            (model_hash, number),
        )
        row = cur.fetchone()
        if row is None:
            raise VersionNotFound(model_hash, number)
        return int(row[0])

    def _read(self, sql: str, params: tuple) -> list[tuple]:
        """All rows of one read-only query, in its own transaction."""
        with self._transaction(write=False) as cur:
            cur.execute(sql, params)
            return cur.fetchall()

    def list_versions(self, model_hash: str) -> list[VersionInfo]:
        check_model_hash(model_hash)
        rows = self._read(
            f"SELECT {_VERSION_COLUMNS} FROM calib_versions WHERE model_hash = ? ORDER BY number",
            (model_hash,),
        )
        return [self._version_info(row) for row in rows]

    def get_version(self, model_hash: str, number: int) -> VersionInfo:
        check_model_hash(model_hash)
        check_number(number)
        rows = self._read(
            f"SELECT {_VERSION_COLUMNS} FROM calib_versions WHERE model_hash = ? AND number = ?",
            (model_hash, number),
        )
        if not rows:
            raise VersionNotFound(model_hash, number)
        return self._version_info(rows[0])

    def load_scores(self, model_hash: str, number: int) -> ScoreTable:
        check_model_hash(model_hash)
        check_number(number)
        with self._transaction(write=False) as cur:
            version_id = self._version_id(cur, model_hash, number)
            cur.execute(
                "SELECT object_name, keypoint_ids, instance_refs, image_hashes, instance_hashes,"
                " groups FROM calib_score_objects WHERE version_id = ? ORDER BY position",
                (version_id,),
            )
            objects = cur.fetchall()
            cur.execute(
                "SELECT object_name, function, n_rows, n_cols, data FROM calib_score_arrays"
                " WHERE version_id = ?",
                (version_id,),
            )
            arrays = cur.fetchall()
            cur.execute(
                "SELECT object_name, feature, n_rows, n_cols, data FROM calib_feature_arrays"
                " WHERE version_id = ?",
                (version_id,),
            )
            features = cur.fetchall()
        return _score_table(objects, arrays, features)

    def active_version(self, model_hash: str) -> Activation | None:
        check_model_hash(model_hash)
        rows = self._read(
            f"SELECT {_ACTIVATION_COLUMNS} FROM calib_activations WHERE model_hash = ?"
            " ORDER BY seq DESC LIMIT 1",
            (model_hash,),
        )
        return self._activation(rows[0]) if rows else None

    def activation_log(self, model_hash: str) -> list[Activation]:
        check_model_hash(model_hash)
        rows = self._read(
            f"SELECT {_ACTIVATION_COLUMNS} FROM calib_activations WHERE model_hash = ? ORDER BY seq",
            (model_hash,),
        )
        return [self._activation(row) for row in rows]

    def change_counter(self) -> int:
        return int(self._read("SELECT value FROM calib_change_counter WHERE id = 1", ())[0][0])

    def ping(self) -> None:
        self.change_counter()

    # -- jobs ------------------------------------------------------------------

    def create_job(self, job: JobRecord, audit: Sequence[NewAuditEntry] = ()) -> JobRecord:
        if not isinstance(job, JobRecord):
            raise TypeError("create_job takes a JobRecord")
        entries = _audit_entries(audit)
        with self._transaction(write=True) as cur:
            cur.execute(
                f"INSERT INTO calib_jobs ({_JOB_COLUMNS}) VALUES (?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?, ?)"
                f" ON CONFLICT (id) DO NOTHING RETURNING {_JOB_COLUMNS}",
                (
                    job.id,
                    job.kind,
                    job.owner,
                    self._time_to_db(job.created_at),
                    *(self._job_value(name, value) for name, value in _job_fields(job)),
                ),
            )
            row = cur.fetchone()
            for entry in entries if row is not None else ():
                self._insert_audit(cur, entry)
        if row is None:
            raise JobExists(job.id)
        return self._job(row)

    def update_job(self, job_id: str, **fields: Any) -> JobRecord:
        _check_job_id(job_id)
        if not is_job_id(job_id):
            raise JobNotFound(job_id)
        changes = {name: check_job_field(name, value) for name, value in fields.items()}
        changes.setdefault("heartbeat_at", now_utc())
        names = sorted(changes)  # column names from the JOB_MUTABLE_FIELDS whitelist only
        assignments = ", ".join(f"{name} = ?" for name in names)
        with self._transaction(write=True) as cur:
            cur.execute(
                f"UPDATE calib_jobs SET {assignments} WHERE id = ? AND state NOT IN ({_FINAL_STATES_SQL})"
                f" RETURNING {_JOB_COLUMNS}",
                (*(self._job_value(name, changes[name]) for name in names), job_id),
            )
            row = cur.fetchone()
            if row is None:
                self._raise_job_unchangeable(cur, job_id)
        return self._job(row)

    def get_job(self, job_id: str) -> JobRecord | None:
        _check_job_id(job_id)
        if not is_job_id(job_id):  # e.g. a NUL character, which PostgreSQL text refuses
            return None
        rows = self._read(f"SELECT {_JOB_COLUMNS} FROM calib_jobs WHERE id = ?", (job_id,))
        return self._job(rows[0]) if rows else None

    def stale_jobs(self, silent_since: datetime, limit: int = 100) -> list[JobRecord]:
        limit = check_number(limit, "stale jobs page size")
        rows = self._read(
            f"SELECT {_JOB_COLUMNS} FROM calib_jobs WHERE state NOT IN ({_FINAL_STATES_SQL})"
            " AND heartbeat_at < ? ORDER BY heartbeat_at LIMIT ?",
            (self._time_to_db(check_job_field("heartbeat_at", silent_since)), limit),
        )
        return [self._job(row) for row in rows]

    def prune_jobs(self, keep: int = KEEP_JOBS, max_age: timedelta = JOB_MAX_AGE) -> int:
        keep = check_number(keep, "jobs to keep")
        if not isinstance(max_age, timedelta) or max_age <= timedelta(0):
            raise ValueError("max_age must be a positive timedelta")
        with self._transaction(write=True) as cur:
            cur.execute(
                "DELETE FROM calib_jobs WHERE heartbeat_at < ?"
                f" OR (state IN ({_FINAL_STATES_SQL}) AND created_at < (SELECT created_at"
                " FROM calib_jobs ORDER BY created_at DESC LIMIT 1 OFFSET ?)) RETURNING id",
                (self._time_to_db(now_utc() - max_age), keep - 1),
            )
            return len(cur.fetchall())

    def _job_value(self, name: str, value: Any) -> Any:
        """One mutable job field as a database value."""
        if name == "errors":
            return codec.encode_json(list(value))
        if name == "result":
            return codec.encode_json(value)
        if name in ("finished_at", "heartbeat_at"):
            return None if value is None else self._time_to_db(value)
        return value

    # -- row mapping -----------------------------------------------------------

    def _version_info(self, row: Sequence[Any]) -> VersionInfo:
        batches = codec.decode_json(row[4])
        return VersionInfo(
            model_hash=row[0],
            number=int(row[1]),
            model_name=row[2],
            normalization=codec.decode_json(row[3]),
            source_batches=tuple(SourceBatch.coerce(b) for b in batches),
            author=row[5],
            note=row[6],
            parent_version=None if row[7] is None else int(row[7]),
            created_at=self._time_from_db(row[8]),
            n_instances=int(row[9]),
            object_counts=codec.decode_json(row[10]),
            functions=tuple(codec.decode_json(row[11])),
            strata=None if row[12] is None else codec.decode_json(row[12]),
        )

    def _job(self, row: Sequence[Any]) -> JobRecord:
        return JobRecord(
            id=row[0],
            kind=row[1],
            owner=row[2],
            created_at=self._time_from_db(row[3]),
            heartbeat_at=self._time_from_db(row[4]),
            state=row[5],
            done=int(row[6]),
            total=int(row[7]),
            errors=tuple(codec.decode_json(row[8])),
            result=codec.decode_json(row[9]),
            finished_at=None if row[10] is None else self._time_from_db(row[10]),
            version=None if row[11] is None else int(row[11]),
        )

    def _audit(self, row: Sequence[Any]) -> AuditEntry:
        return AuditEntry(
            seq=int(row[0]),
            at=self._time_from_db(row[1]),
            model_hash=row[2],
            who=row[3],
            action=row[4],
            outcome=row[5],
            version=None if row[6] is None else int(row[6]),
            previous_version=None if row[7] is None else int(row[7]),
            reason=row[8],
            client=row[9],
            details=codec.decode_json(row[10]),
        )

    def _coverage_audit(self, row: Sequence[Any]) -> CoverageAudit:
        return CoverageAudit(
            id=int(row[0]),
            model_hash=row[1],
            version=int(row[2]),
            created_at=self._time_from_db(row[3]),
            who=row[4],
            batch_sha256=row[5],
            n_instances=int(row[6]),
            report=codec.decode_json(row[7]),
        )

    def _activation(self, row: Sequence[Any]) -> Activation:
        return Activation(
            seq=int(row[0]),
            model_hash=row[1],
            version=int(row[2]),
            activated_at=self._time_from_db(row[3]),
            who=row[4],
            reason=row[5],
        )


_MAX_SEQ = 2**63 - 1


def _check_types(value: object, kind: type, what: str) -> None:
    if value is not None and not isinstance(value, kind):
        raise TypeError(f"{what} must be a {kind.__name__} or None")


def _audit_entries(entries: Sequence[NewAuditEntry]) -> tuple[NewAuditEntry, ...]:
    entries = tuple(entries)
    for entry in entries:
        _check_types(entry, NewAuditEntry, "each audit entry")
    return entries


class _NotFirst(Exception):
    """Aborts create_first_version's transaction when the model already has a version."""


def _encoded_blocks(new: object, scores: object, method: str) -> list[EncodedBlock]:
    """The score blocks of a version to write, after checking the arguments' types."""
    if not isinstance(new, NewVersion) or not isinstance(scores, ScoreTable):
        raise TypeError(f"{method} takes a NewVersion and a ScoreTable")
    return [encode_block(i, block) for i, block in enumerate(scores.objects)]


def _check_activation_text(who: object, reason: object) -> None:
    if not isinstance(who, str) or not who.strip():
        raise ValueError("who must be a non-empty string")
    if not isinstance(reason, str):
        raise TypeError("reason must be a string")


def _check_job_id(job_id: object) -> None:
    if not isinstance(job_id, str):
        raise TypeError(f"job id must be a string, got {type(job_id).__name__}")


def _job_fields(job: JobRecord) -> list[tuple[str, Any]]:
    """The mutable fields of a job, in _JOB_COLUMNS order."""
    return [("heartbeat_at", job.heartbeat_at), *job.progress_fields().items()]


def _score_table(objects: list[Any], arrays: list[Any], features: list[Any]) -> ScoreTable:
    return ScoreTable(tuple(_blocks(objects, _matrices(arrays), _matrices(features))))


def _matrices(arrays: list[Any]) -> dict[str, dict[str, Any]]:
    """Rows (object_name, name, n_rows, n_cols, data) -> object -> name -> matrix."""
    matrices: dict[str, dict[str, Any]] = {}
    for object_name, name, rows, cols, data in arrays:
        matrices.setdefault(object_name, {})[name] = codec.decode_matrix(data, rows, cols)
    return matrices


def _blocks(
    objects: list[Any], matrices: dict[str, dict[str, Any]], features: dict[str, dict[str, Any]]
) -> Iterator[ObjectScores]:
    for object_name, keypoint_ids, instance_refs, image_hashes, instance_hashes, groups in objects:
        yield ObjectScores(
            object_name=object_name,
            keypoint_ids=codec.decode_ids(keypoint_ids),
            instance_refs=codec.decode_refs(instance_refs),
            scores=matrices.get(object_name, {}),
            image_hashes=codec.decode_digests(image_hashes),
            instance_hashes=codec.decode_digests(instance_hashes),
            features=features.get(object_name, {}),
            groups=codec.decode_refs(groups) if groups is not None else (),
        )
