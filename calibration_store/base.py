"""The backend-independent interface every calibration store implements."""

from __future__ import annotations

from abc import ABC, abstractmethod
from collections.abc import Sequence
from datetime import datetime, timedelta
from types import TracebackType
from typing import Any

from .models import (
    Activation,
    ActivationIntent,
    AuditEntry,
    CoverageAudit,
    JobCompletion,
    JobRecord,
    NewAuditEntry,
    NewCoverageAudit,
    NewVersion,
    ScoreTable,
    VersionInfo,
)

#: prune_jobs defaults: keep the newest KEEP_JOBS jobs and anything alive within JOB_MAX_AGE
KEEP_JOBS = 1000
JOB_MAX_AGE = timedelta(days=7)


class CalibrationStore(ABC):
    """Versioned, durable storage of calibration scores. Thread-safe.

    Versions are immutable and numbered 1, 2, 3, ... per model hash without gaps.
    Activation is an append-only log; the active version of a model is the version
    named by its latest activation (None until the first activation).
    """

    @abstractmethod
    def create_version(
        self,
        new: NewVersion,
        scores: ScoreTable,
        *,
        activation: ActivationIntent | None = None,
        job: JobCompletion | None = None,
        audit: Sequence[NewAuditEntry] = (),
    ) -> VersionInfo:
        """Store a new version atomically and return its metadata (number, created_at).

        In the same transaction, optionally: activate it (``activation``), mark the job that
        produced it succeeded with the version number (``job``; JobFinished or JobNotFound,
        and nothing is written, if that job is already final or gone), and append ``audit``
        entries (an entry's version None means the new version). A process killed at any
        point leaves all of it or none of it.
        Raises VersionNotFound if new.parent_version does not exist for new.model_hash, and
        DuplicateVersion if a version of the model has new.content_key (one version per content
        key, whatever the number of writers).
        """

    @abstractmethod
    def create_first_version(
        self, new: NewVersion, scores: ScoreTable, who: str, reason: str = ""
    ) -> VersionInfo | None:
        """Store ``new`` as the model's version 1 and activate it, in one transaction.

        Returns None, writing nothing, if the model already has (or had) a version: of
        several processes bootstrapping the same store at once, exactly one succeeds.
        """

    @abstractmethod
    def list_versions(self, model_hash: str) -> list[VersionInfo]:
        """Metadata of every version of a model, by increasing number ([] if none)."""

    @abstractmethod
    def get_version(self, model_hash: str, number: int) -> VersionInfo:
        """Metadata of one version; raises VersionNotFound."""

    @abstractmethod
    def load_scores(self, model_hash: str, number: int) -> ScoreTable:
        """The scores of one version, as read-only numpy arrays; raises VersionNotFound."""

    @abstractmethod
    def activate(
        self, model_hash: str, number: int, who: str, reason: str = "", audit: Sequence[NewAuditEntry] = ()
    ) -> Activation:
        """Append an activation of an existing version to the log, and ``audit`` entries, in one
        transaction; raises VersionNotFound."""

    @abstractmethod
    def append_audit(self, entry: NewAuditEntry) -> AuditEntry:
        """Append one entry to the audit trail (append-only: entries are never changed)."""

    @abstractmethod
    def audit_log(self, model_hash: str, before: int | None = None, limit: int = 100) -> list[AuditEntry]:
        """Audit entries of a model, newest first: at most ``limit`` with seq < ``before``."""

    @abstractmethod
    def create_coverage_audit(self, new: NewCoverageAudit, job: JobCompletion | None = None) -> CoverageAudit:
        """Store a coverage audit (immutable) and return it with its id and created_at.

        With ``job``, in the same transaction, mark that job succeeded with ``"audit": <id>``
        added to its result (JobFinished or JobNotFound, and nothing is written, if it is final
        or gone). Raises VersionNotFound if the audited version does not exist.
        """

    @abstractmethod
    def coverage_audits(
        self, model_hash: str, before: int | None = None, limit: int = 100
    ) -> list[CoverageAudit]:
        """Coverage audits of a model, newest first: at most ``limit`` with id < ``before``."""

    @abstractmethod
    def coverage_audit(self, model_hash: str, audit_id: int) -> CoverageAudit | None:
        """One coverage audit of a model, or None if there is none with this id."""

    @abstractmethod
    def active_version(self, model_hash: str) -> Activation | None:
        """The latest activation of a model, or None if it was never activated."""

    @abstractmethod
    def activation_log(self, model_hash: str) -> list[Activation]:
        """Every activation of a model, oldest first."""

    @abstractmethod
    def change_counter(self) -> int:
        """A store-wide integer that grows on every version creation and activation.

        One cheap query: poll it (about once a second) to learn that another replica
        changed something, then re-read active_version.
        """

    @abstractmethod
    def create_job(self, job: JobRecord, audit: Sequence[NewAuditEntry] = ()) -> JobRecord:
        """Store a new background job as given, and ``audit`` entries, in one transaction; raises
        JobExists (writing nothing) if its id is taken."""

    @abstractmethod
    def update_job(self, job_id: str, **fields: Any) -> JobRecord:
        """Change mutable fields of an unfinished job (see JOB_MUTABLE_FIELDS); return the row.

        Every update is a sign of life: heartbeat_at is set to now unless given.
        `update_job(job_id)` only refreshes the heartbeat. Raises JobNotFound, and
        JobFinished for a job already in a final state (finished jobs never change).
        """

    @abstractmethod
    def get_job(self, job_id: str) -> JobRecord | None:
        """The stored job, or None if there is none with this id (or it was pruned)."""

    @abstractmethod
    def stale_jobs(self, silent_since: datetime, limit: int = 100) -> list[JobRecord]:
        """Unfinished jobs whose heartbeat is older than ``silent_since`` (their process stopped,
        or stopped writing), oldest heartbeat first, at most ``limit``."""

    @abstractmethod
    def prune_jobs(self, keep: int = KEEP_JOBS, max_age: timedelta = JOB_MAX_AGE) -> int:
        """Delete old jobs and return how many were deleted.

        A job is deleted when its heartbeat (its last write) is older than max_age, or
        when it is finished and at least `keep` jobs were created after it. A live
        unfinished job is never deleted.
        """

    @abstractmethod
    def ping(self) -> None:
        """Check the database answers (readiness); raises StoreUnavailable otherwise."""

    @abstractmethod
    def close(self) -> None:
        """Release connections. The store must not be used afterwards."""

    def __enter__(self) -> CalibrationStore:
        return self

    def __exit__(
        self,
        exc_type: type[BaseException] | None,
        exc: BaseException | None,
        tb: TracebackType | None,
    ) -> None:
        self.close()
