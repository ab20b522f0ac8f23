"""Versioned, durable storage of calibration scores (knows nothing about heatmaps).

Open a store from one URL (migrations run on open, safely from several processes)::

    from calibration_store import open_store, NewVersion, ObjectScores, ScoreTable

    store = open_store("sqlite:///var/lib/keypoints/calibration.db")   # or postgresql://...
    info = store.create_version(
        NewVersion(model_hash=sha, model_name="hourglass", normalization={"mode": "anchor"},
                   source_batches=[{"name": "b1.zip", "sha256": digest, "instances": 120}],
                   author="alice", note="first batch", parent_version=None),
        ScoreTable((ObjectScores("mug", keypoint_ids=[0, 1, 2], instance_refs=refs,
                                 scores={"peak": p, "var": v, "cov": c}),)),
    )                                    # p, v, c: (n_instances, 3) float64, NaN = unlabeled
    store.activate(sha, info.number, who="alice", reason="initial")
    active = store.active_version(sha)   # Activation | None
    table = store.load_scores(sha, active.version)

URLs: ``sqlite:///abs/path.db`` (also ``sqlite:////abs/path.db``) and
``sqlite:relative/path.db`` (parent directories are created), ``postgresql://...``
(needs the ``postgres`` extra: psycopg 3 + psycopg_pool).

CalibrationStore (thread-safe; also a context manager that closes):
- ``create_version(new: NewVersion, scores: ScoreTable, *, activation=None, job=None,
  audit=()) -> VersionInfo``: one transaction; numbers are 1, 2, ... per model hash,
  distinct and gap-free under concurrent writers; a writer killed mid-way leaves nothing.
  In the same transaction it can activate the new version (``ActivationIntent``), mark
  the job that produced it succeeded with its number (``JobCompletion``) and append audit
  entries. ``created_at`` is set by the store (UTC). Raises VersionNotFound if
  ``parent_version`` does not exist, and DuplicateVersion (writing nothing) if a version of the
  model has the same ``content_key``: identical content makes one version, whatever the number
  of processes and replicas writing at once (a unique index; None: no rule).
- ``create_first_version(new, scores, who, reason="") -> VersionInfo | None``: version 1
  stored and activated in one transaction, or None (nothing written) if the model has
  or had a version: concurrent bootstraps of one store succeed exactly once.
- ``list_versions(model_hash) -> list[VersionInfo]`` (by number),
  ``get_version(model_hash, number) -> VersionInfo``,
  ``load_scores(model_hash, number) -> ScoreTable`` (read-only arrays, bit-exact).
- ``activate(model_hash, number, who, reason="", audit=()) -> Activation``: appends to
  the log (and the audit entries, same transaction); rollback = activating an older number.
- ``append_audit(NewAuditEntry) -> AuditEntry``, ``audit_log(model_hash, before=None,
  limit=100) -> list[AuditEntry]`` (newest first): the append-only audit trail.
  ``active_version(model_hash) -> Activation | None`` is the latest activation;
  ``activation_log(model_hash) -> list[Activation]`` oldest first.
- ``change_counter() -> int``: grows with every creation and activation, store-wide;
  poll it (one tiny query) to notice changes made by other replicas.
- ``create_job(job: JobRecord, audit=()) -> JobRecord`` (JobExists if the id is taken; the
  audit entries in the same transaction),
  ``update_job(job_id, **fields) -> JobRecord`` (state, done, total, errors, result,
  finished_at, version, heartbeat_at; heartbeat_at defaults to now, so every write is a
  sign of life; JobNotFound; JobFinished for a job in a final state: finished jobs never
  change), ``get_job(job_id) -> JobRecord | None``: background jobs, visible
  to every process sharing the store. ``stale_jobs(silent_since, limit=100)``: unfinished
  jobs whose heartbeat is older (their process stopped), for another to take over.
  ``prune_jobs(keep=1000, max_age=7 days) -> int``
  deletes jobs whose heartbeat is older than max_age, and finished jobs with ``keep``
  newer jobs after them; a live unfinished job is never deleted.
- ``ping() -> None`` (raises StoreUnavailable), ``close() -> None``.

Data classes (frozen, validated on construction: ValueError/TypeError says what to fix):
- ``SourceBatch(name, sha256, instances)``; NewVersion also accepts plain dicts.
- ``NewVersion(model_hash, model_name, normalization: dict, source_batches, author,
  note="", parent_version: int | None = None, strata=None, content_key: str | None = None)``.
- ``ObjectScores(object_name, keypoint_ids: (k,) int, instance_refs: (n,) str,
  scores: {function: (n, k) float64}, image_hashes=(), instance_hashes=())``: the
  hashes are (n,) sha256 hex digests, or empty when unknown; scores finite or NaN
  only; functions are lowercase names (the service uses DEFAULT_FUNCTIONS = peak, var, cov).
- ``ScoreTable(objects: tuple[ObjectScores, ...])``: unique object names, the same
  functions in every block; ``.object(name)``, ``.n_instances``, ``.functions``.
- ``VersionInfo(model_hash, number, model_name, normalization, source_batches,
  author, note, parent_version, created_at, n_instances, object_counts, functions)``.
- ``Activation(seq, model_hash, version, activated_at, who, reason)``.
- ``JobRecord(id, kind, owner, created_at, heartbeat_at, state="queued", done=0,
  total=0, errors=(), result={}, finished_at=None, version=None)``: state is one of
  JOB_STATES (queued, running, succeeded, failed, interrupted); times are timezone-aware.
- ``ActivationIntent(who, reason)``, ``JobCompletion(job_id, result)``,
  ``NewAuditEntry(model_hash, who, action, outcome, version=None, previous_version=None,
  reason="", client="", details={})`` and the stored ``AuditEntry`` (+ seq, at).

Coverage audits (immutable, like versions):
- ``create_coverage_audit(NewCoverageAudit(model_hash, version, who, batch_sha256,
  n_instances, report), job=None) -> CoverageAudit`` (+ id, created_at); with ``job``
  (a JobCompletion) the job is marked succeeded with ``"audit": <id>`` in its result in the
  same transaction. VersionNotFound if the audited version does not exist.
- ``coverage_audits(model_hash, before=None, limit=100) -> list[CoverageAudit]`` newest
  first (id < before), ``coverage_audit(model_hash, audit_id) -> CoverageAudit | None``.

Feedback (calibration_store/feedback_records.py): ``retain_predictions([RetainedPrediction],
max_rows)`` (one transaction), ``retained_prediction(id)``, ``oldest_retained()``,
``label_prediction(id, labels, who, at, audit, LabelVerdicts) -> LabelOutcome`` (once per row,
with its audit entry and verdicts), ``labelled_predictions(model_hash, limit)`` (in label order),
``labelled_since(model_hash, since) -> [(id, labelled_at)]``, ``label_verdicts(ids)`` and
``retained_predictions(ids)`` (new labels, read incrementally),
``adaptive_state(key)``
and ``save_adaptive_state(key, steps_before, AdaptiveState) -> bool`` (compare-and-set on the step count).

Errors: StoreError > VersionNotFound (also a LookupError; HTTP 404), DuplicateVersion, JobNotFound
(a LookupError), JobExists (a ValueError), JobFinished, SchemaVersionError (database migrated by
newer code), StoreUnavailable (HTTP 503), StoreFull (a StoreUnavailable: the database's disk is
full; HTTP 507).
Versions, scores, activations and audit entries are immutable (database triggers refuse
UPDATE and DELETE); only unfinished job rows change.
"""

from .base import CalibrationStore
from .errors import (
    DuplicateVersion,
    JobExists,
    JobFinished,
    JobNotFound,
    SchemaVersionError,
    StoreError,
    StoreFull,
    StoreUnavailable,
    VersionNotFound,
)
from .factory import open_store, sqlite_path, store_location
from .feedback_records import AdaptiveState, LabelOutcome, LabelVerdicts, RetainedPrediction
from .models import (
    DEFAULT_FUNCTIONS,
    FINAL_JOB_STATES,
    JOB_STATES,
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
)

__all__ = [
    "DEFAULT_FUNCTIONS",
    "DuplicateVersion",
    "FINAL_JOB_STATES",
    "JOB_STATES",
    "Activation",
    "ActivationIntent",
    "AdaptiveState",
    "AuditEntry",
    "CalibrationStore",
    "CoverageAudit",
    "JobCompletion",
    "JobExists",
    "JobFinished",
    "JobNotFound",
    "JobRecord",
    "MonitorShare",
    "LabelOutcome",
    "LabelVerdicts",
    "NewAuditEntry",
    "NewCoverageAudit",
    "NewVersion",
    "ObjectScores",
    "SchemaVersionError",
    "RetainedPrediction",
    "ScoreTable",
    "SourceBatch",
    "StoreError",
    "StoreFull",
    "StoreUnavailable",
    "VersionInfo",
    "VersionNotFound",
    "open_store",
    "sqlite_path",
    "store_location",
]
