"""Forward-only schema migrations, applied when a store opens.

Each backend runs `apply_migrations` inside one transaction holding a database-wide
lock (SQLite: BEGIN IMMEDIATE; PostgreSQL: pg_advisory_xact_lock), so concurrent
openers apply each migration exactly once and see either none or all of it.
To change the schema append a Migration; never edit a released one.
"""

from __future__ import annotations

from dataclasses import dataclass
from datetime import UTC, datetime
from typing import Any

from .errors import SchemaVersionError
from .feedback_records import FEEDBACK_TABLES, VERDICTS_STATEMENTS, VERDICTS_TABLE, feedback_tables


@dataclass(frozen=True)
class Migration:
    version: int
    description: str
    statements: tuple[str, ...]


def _initial(blob: str, id_column: str, seq_column: str, timestamp: str) -> tuple[str, ...]:
    return (
        """CREATE TABLE calib_models (
            model_hash TEXT PRIMARY KEY,
            last_number INTEGER NOT NULL CHECK (last_number >= 1)
        )""",
        f"""CREATE TABLE calib_versions (
            {id_column},
            model_hash TEXT NOT NULL REFERENCES calib_models (model_hash),
            number INTEGER NOT NULL CHECK (number >= 1),
            model_name TEXT NOT NULL,
            normalization TEXT NOT NULL,
            source_batches TEXT NOT NULL,
            author TEXT NOT NULL,
            note TEXT NOT NULL,
            parent_number INTEGER,
            created_at {timestamp} NOT NULL,
            n_instances BIGINT NOT NULL,
            object_counts TEXT NOT NULL,
            functions TEXT NOT NULL,
            UNIQUE (model_hash, number),
            FOREIGN KEY (model_hash, parent_number) REFERENCES calib_versions (model_hash, number)
        )""",
        f"""CREATE TABLE calib_score_objects (
            version_id BIGINT NOT NULL REFERENCES calib_versions (id),
            position INTEGER NOT NULL,
            object_name TEXT NOT NULL,
            n_instances BIGINT NOT NULL,
            keypoint_ids {blob} NOT NULL,
            instance_refs TEXT NOT NULL,
            PRIMARY KEY (version_id, object_name),
            UNIQUE (version_id, position)
        )""",
        f"""CREATE TABLE calib_score_arrays (
            version_id BIGINT NOT NULL,
            object_name TEXT NOT NULL,
            function TEXT NOT NULL,
            n_rows BIGINT NOT NULL,
            n_cols INTEGER NOT NULL,
            data {blob} NOT NULL,
            PRIMARY KEY (version_id, object_name, function),
            FOREIGN KEY (version_id, object_name)
                REFERENCES calib_score_objects (version_id, object_name)
        )""",
        f"""CREATE TABLE calib_activations (
            {seq_column},
            model_hash TEXT NOT NULL,
            number INTEGER NOT NULL,
            activated_at {timestamp} NOT NULL,
            who TEXT NOT NULL,
            reason TEXT NOT NULL,
            FOREIGN KEY (model_hash, number) REFERENCES calib_versions (model_hash, number)
        )""",
        "CREATE INDEX calib_activations_by_model ON calib_activations (model_hash, seq)",
        """CREATE TABLE calib_change_counter (
            id INTEGER PRIMARY KEY CHECK (id = 1),
            value BIGINT NOT NULL
        )""",
        "INSERT INTO calib_change_counter (id, value) VALUES (1, 0)",
    )


def _jobs(timestamp: str) -> tuple[str, ...]:
    """Background jobs, so that any process of any replica can report them (mutable rows)."""
    return (
        f"""CREATE TABLE calib_jobs (
            id TEXT PRIMARY KEY,
            kind TEXT NOT NULL,
            owner TEXT NOT NULL,
            created_at {timestamp} NOT NULL,
            heartbeat_at {timestamp} NOT NULL,
            state TEXT NOT NULL CHECK (state IN ('queued', 'running', 'succeeded', 'failed')),
            done BIGINT NOT NULL CHECK (done >= 0),
            total BIGINT NOT NULL CHECK (total >= 0),
            errors TEXT NOT NULL,
            result TEXT NOT NULL,
            finished_at {timestamp}
        )""",
        "CREATE INDEX calib_jobs_by_created ON calib_jobs (created_at)",
        "CREATE INDEX calib_jobs_by_heartbeat ON calib_jobs (heartbeat_at)",
    )


_IMMUTABLE_TABLES = ("calib_versions", "calib_score_objects", "calib_score_arrays", "calib_activations")


def _sqlite_immutability(tables: tuple[str, ...] = _IMMUTABLE_TABLES) -> tuple[str, ...]:
    return tuple(
        f"""CREATE TRIGGER {table}_immutable_{op.lower()} BEFORE {op} ON {table}
            BEGIN SELECT RAISE(ABORT, 'calibration store history is immutable'); END"""
        for table in tables
        for op in ("UPDATE", "DELETE")
    )


def _postgres_triggers(tables: tuple[str, ...]) -> tuple[str, ...]:
    return tuple(
        f"""CREATE TRIGGER {table}_immutable BEFORE UPDATE OR DELETE ON {table}
            FOR EACH ROW EXECUTE FUNCTION calib_refuse_change()"""
        for table in tables
    )


def _postgres_immutability() -> tuple[str, ...]:
    function = """CREATE FUNCTION calib_refuse_change() RETURNS trigger LANGUAGE plpgsql AS $$
        BEGIN RAISE EXCEPTION 'calibration store history is immutable'; END $$"""
    return (function, *_postgres_triggers(_IMMUTABLE_TABLES))


_JOB_STATES_V3 = "'queued', 'running', 'succeeded', 'failed', 'interrupted'"
_JOB_COLUMNS_V2 = "id, kind, owner, created_at, heartbeat_at, state, done, total, errors, result, finished_at"


def _content_hashes_and_audit(blob: str, seq_column: str, timestamp: str) -> tuple[str, ...]:
    """Per-instance content hashes (duplicate checks) and the append-only audit trail."""
    return (
        f"ALTER TABLE calib_score_objects ADD COLUMN image_hashes {blob}",
        f"ALTER TABLE calib_score_objects ADD COLUMN instance_hashes {blob}",
        f"""CREATE TABLE calib_audit (
            {seq_column},
            at {timestamp} NOT NULL,
            model_hash TEXT NOT NULL,
            who TEXT NOT NULL,
            action TEXT NOT NULL,
            outcome TEXT NOT NULL,
            version INTEGER,
            previous_version INTEGER,
            reason TEXT NOT NULL,
            client TEXT NOT NULL,
            details TEXT NOT NULL
        )""",
        "CREATE INDEX calib_audit_by_model ON calib_audit (model_hash, seq)",
    )


def _sqlite_jobs_v3() -> tuple[str, ...]:
    """SQLite cannot change a CHECK constraint: rebuild calib_jobs with the new state and column."""
    return (
        f"""CREATE TABLE calib_jobs_v3 (
            id TEXT PRIMARY KEY,
            kind TEXT NOT NULL,
            owner TEXT NOT NULL,
            created_at TEXT NOT NULL,
            heartbeat_at TEXT NOT NULL,
            state TEXT NOT NULL CHECK (state IN ({_JOB_STATES_V3})),
            done BIGINT NOT NULL CHECK (done >= 0),
            total BIGINT NOT NULL CHECK (total >= 0),
            errors TEXT NOT NULL,
            result TEXT NOT NULL,
            finished_at TEXT,
            version INTEGER
        )""",
        f"INSERT INTO calib_jobs_v3 ({_JOB_COLUMNS_V2}) SELECT {_JOB_COLUMNS_V2} FROM calib_jobs",
        "DROP TABLE calib_jobs",
        "ALTER TABLE calib_jobs_v3 RENAME TO calib_jobs",
        "CREATE INDEX calib_jobs_by_created ON calib_jobs (created_at)",
        "CREATE INDEX calib_jobs_by_heartbeat ON calib_jobs (heartbeat_at)",
    )


def _postgres_jobs_v3() -> tuple[str, ...]:
    return (
        "ALTER TABLE calib_jobs DROP CONSTRAINT calib_jobs_state_check",
        f"ALTER TABLE calib_jobs ADD CONSTRAINT calib_jobs_state_check CHECK (state IN ({_JOB_STATES_V3}))",
        "ALTER TABLE calib_jobs ADD COLUMN version INTEGER",
    )


def _features_and_groups(blob: str) -> tuple[str, ...]:
    """Label-free heatmap features of every calibration instance, and caller group labels."""
    return (
        f"""CREATE TABLE calib_feature_arrays (
            version_id BIGINT NOT NULL,
            object_name TEXT NOT NULL,
            feature TEXT NOT NULL,
            n_rows BIGINT NOT NULL,
            n_cols INTEGER NOT NULL,
            data {blob} NOT NULL,
            PRIMARY KEY (version_id, object_name, feature),
            FOREIGN KEY (version_id, object_name)
                REFERENCES calib_score_objects (version_id, object_name)
        )""",
        "ALTER TABLE calib_score_objects ADD COLUMN groups TEXT",
    )


_FEATURES_AND_GROUPS = "heatmap features and group labels of calibration instances"


def _coverage_audits(id_column: str, timestamp: str) -> tuple[str, ...]:
    """Coverage audits of versions on labeled batches: immutable, like the versions they audit."""
    return (
        f"""CREATE TABLE calib_coverage_audits (
            {id_column},
            model_hash TEXT NOT NULL,
            version INTEGER NOT NULL,
            created_at {timestamp} NOT NULL,
            who TEXT NOT NULL,
            batch_sha256 TEXT NOT NULL,
            n_instances BIGINT NOT NULL CHECK (n_instances >= 0),
            report TEXT NOT NULL,
            FOREIGN KEY (model_hash, version) REFERENCES calib_versions (model_hash, number)
        )""",
        "CREATE INDEX calib_coverage_audits_by_model ON calib_coverage_audits (model_hash, id)",
    )


_COVERAGE_AUDITS = "coverage audits"

# Mondrian strata of a version (spec, difficulty-bin edges and counts) as JSON; NULL = none.
_STRATA = "Mondrian strata of calibration versions"
_STRATA_COLUMN = ("ALTER TABLE calib_versions ADD COLUMN strata TEXT",)

# One version per content (the service's digest of its instances, strata and scoring settings):
# a rule of the store, so that writers in several processes and replicas cannot both store it.
# NULL (versions stored before, and copies made on purpose) is never equal to another NULL.
_CONTENT_KEY = "one version per content key"
_CONTENT_KEY_STATEMENTS = (
    "ALTER TABLE calib_versions ADD COLUMN content_key TEXT",
    "CREATE UNIQUE INDEX calib_versions_by_content ON calib_versions (model_hash, content_key)",
)


def _monitor_shares(blob: str, timestamp: str) -> tuple[str, ...]:
    """What each replica's monitors saw lately (drift windows, looks), one row per replica and kind,
    replaced in place: any replica merges them to answer for the fleet."""
    return (
        f"""CREATE TABLE calib_monitor_shares (
            model_hash TEXT NOT NULL,
            kind TEXT NOT NULL,
            replica TEXT NOT NULL,
            updated_at {timestamp} NOT NULL,
            payload {blob} NOT NULL,
            PRIMARY KEY (model_hash, kind, replica)
        )""",
    )


_MONITOR_SHARES = "what each replica's monitors saw, merged on read"

SQLITE_MIGRATIONS: tuple[Migration, ...] = (
    Migration(
        1,
        "versions, score blobs, activation log, change counter",
        _initial(
            blob="BLOB",
            id_column="id INTEGER PRIMARY KEY",
            seq_column="seq INTEGER PRIMARY KEY AUTOINCREMENT",
            timestamp="TEXT",
        )
        + _sqlite_immutability(),
    ),
    Migration(2, "background jobs", _jobs(timestamp="TEXT")),
    Migration(
        3,
        "content hashes, audit trail, interrupted jobs and the version a job produced",
        _content_hashes_and_audit("BLOB", "seq INTEGER PRIMARY KEY AUTOINCREMENT", "TEXT")
        + _sqlite_immutability(("calib_audit",))
        + _sqlite_jobs_v3(),
    ),
    Migration(
        4,
        _FEATURES_AND_GROUPS,
        _features_and_groups("BLOB") + _sqlite_immutability(("calib_feature_arrays",)),
    ),
    Migration(
        5,
        _COVERAGE_AUDITS,
        _coverage_audits("id INTEGER PRIMARY KEY AUTOINCREMENT", "TEXT")
        + _sqlite_immutability(("calib_coverage_audits",)),
    ),
    Migration(6, _STRATA, _STRATA_COLUMN),
    Migration(7, _CONTENT_KEY, _CONTENT_KEY_STATEMENTS),
    Migration(8, _MONITOR_SHARES, _monitor_shares("BLOB", "TEXT")),
    Migration(9, FEEDBACK_TABLES, feedback_tables("TEXT")),
    Migration(10, VERDICTS_TABLE, VERDICTS_STATEMENTS),
)

POSTGRES_MIGRATIONS: tuple[Migration, ...] = (
    Migration(
        1,
        "versions, score blobs, activation log, change counter",
        _initial(
            blob="BYTEA",
            id_column="id BIGINT GENERATED ALWAYS AS IDENTITY PRIMARY KEY",
            seq_column="seq BIGINT GENERATED ALWAYS AS IDENTITY PRIMARY KEY",
            timestamp="TIMESTAMPTZ",
        )
        + (
            # score blobs are incompressible floats: skip the compression attempt
            "ALTER TABLE calib_score_arrays ALTER COLUMN data SET STORAGE EXTERNAL",
        )
        + _postgres_immutability(),
    ),
    Migration(2, "background jobs", _jobs(timestamp="TIMESTAMPTZ")),
    Migration(
        3,
        "content hashes, audit trail, interrupted jobs and the version a job produced",
        _content_hashes_and_audit(
            "BYTEA", "seq BIGINT GENERATED ALWAYS AS IDENTITY PRIMARY KEY", "TIMESTAMPTZ"
        )
        + _postgres_triggers(("calib_audit",))
        + _postgres_jobs_v3(),
    ),
    Migration(
        4,
        _FEATURES_AND_GROUPS,
        _features_and_groups("BYTEA")
        + ("ALTER TABLE calib_feature_arrays ALTER COLUMN data SET STORAGE EXTERNAL",)
        + _postgres_triggers(("calib_feature_arrays",)),
    ),
    Migration(
        5,
        _COVERAGE_AUDITS,
        _coverage_audits("id BIGINT GENERATED ALWAYS AS IDENTITY PRIMARY KEY", "TIMESTAMPTZ")
        + _postgres_triggers(("calib_coverage_audits",)),
    ),
    Migration(6, _STRATA, _STRATA_COLUMN),
    Migration(7, _CONTENT_KEY, _CONTENT_KEY_STATEMENTS),
    Migration(8, _MONITOR_SHARES, _monitor_shares("BYTEA", "TIMESTAMPTZ")),
    Migration(9, FEEDBACK_TABLES, feedback_tables("TIMESTAMPTZ")),
    Migration(10, VERDICTS_TABLE, VERDICTS_STATEMENTS),
)


def apply_migrations(cur: Any, migrations: tuple[Migration, ...]) -> int:
    """Apply pending migrations through `cur` (inside the caller's locked transaction).

    Returns the schema version afterwards. Raises SchemaVersionError if the database
    was migrated by newer code.
    """
    cur.execute(
        "CREATE TABLE IF NOT EXISTS calib_schema_version ("
        " version INTEGER PRIMARY KEY, description TEXT NOT NULL, applied_at TEXT NOT NULL)"
    )
    cur.execute("SELECT COALESCE(MAX(version), 0) FROM calib_schema_version")
    current = int(cur.fetchone()[0])
    latest = migrations[-1].version
    if current > latest:
        raise SchemaVersionError(
            f"database schema version {current} is newer than this code ({latest}); upgrade"
        )
    for migration in migrations:
        if migration.version > current:
            _apply_one(cur, migration)
    return latest


def _apply_one(cur: Any, migration: Migration) -> None:
    for statement in migration.statements:
        cur.execute(statement)
    cur.execute(
        "INSERT INTO calib_schema_version (version, description, applied_at) VALUES (?, ?, ?)",
        (migration.version, migration.description, datetime.now(UTC).isoformat()),
    )
