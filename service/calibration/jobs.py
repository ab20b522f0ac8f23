"""Background calibration jobs: accepted after the intake (``CalibrationJobs.accept``), run
as one step that turns the validated batch into a version (``CalibrationJobs._job``), retried
from their kept upload when a crash interrupted them (``CalibrationJobs.retry``); run on this
process's worker pool (``JobRunner``, which runs coverage audits too), reported from the store.

Any process of any replica answers for any job, because the job's row in the calibration
store is what clients see:
- the row is created before the upload's 202 is returned, and state changes (running,
  succeeded, failed) are written at once; the final write is retried, then kept in memory
  and retried by the writer thread until it lands;
- progress is written by one writer thread, at most once per PROGRESS_WRITE_S per job, so
  scoring never waits on the store and a failed write only logs a warning;
- every write refreshes the row's heartbeat, and an unfinished job is rewritten at least
  every HEARTBEAT_S even without progress;
- an unfinished job whose heartbeat is older than STALE_AFTER is reported interrupted:
  the process running it stopped. A calibration version is written in the job's last step,
  in the same transaction that marks the job succeeded (versions.create_version), so an
  interrupted job stored nothing; its upload is kept and it can be retried;
- a finished job never changes (the store refuses it): a retry marks the interrupted job
  finished first, so the process presumed dead can no longer complete it;
- when the service stops, its unfinished jobs are marked interrupted at once rather than
  waited for (their uploads are kept for a retry), and a running one stops scoring at its
  next image (``JobCancelled``, raised by its progress report).
"""

from __future__ import annotations

import logging
import threading
import time
import uuid
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import asdict, dataclass, replace
from datetime import UTC, datetime, timedelta
from pathlib import Path
from typing import Any

from calibration_store import (
    CalibrationStore,
    JobFinished,
    JobNotFound,
    JobRecord,
    NewAuditEntry,
    StoreError,
    StoreFull,
    StoreUnavailable,
)
from calibration_store.faults import fill_disk_point
from service.calibration.intake import Intake, IntakeRules, UploadOptions, ValidatedBatch
from service.calibration.registry import CalibrationRegistry
from service.calibration.uploads import RETRYABLE, JobFolder, UploadWorkspace, retryable
from service.calibration.versions import VersionRules, create_version
from service.detector.session import Detector
from service.errors import (
    Conflict,
    NotFound,
    ServiceError,
    StoreUnreachable,
    Unavailable,
    disk_full_refused,
)
from service.infra.audit_trail import AuditTrail, Operator, written
from service.infra.metrics import CALIBRATION_JOBS
from service.infra.processes import process_owner

log = logging.getLogger(__name__)
JOB_KIND = "calibration"

#: progress reaches the store at most this often per job (plus the final state)
PROGRESS_WRITE_S = 1.0
#: an unfinished job of a live process is rewritten at least this often
HEARTBEAT_S = 10.0
#: an unfinished job silent for longer is reported failed (its process stopped)
STALE_AFTER = timedelta(seconds=60)
#: attempts at writing a job's final state before leaving it to the writer thread
FINAL_WRITE_ATTEMPTS = 4
RETRY_DELAY_S = 0.25
_TICK_S = 0.25


def reported(job: JobRecord, now: datetime, stale_after: timedelta = STALE_AFTER) -> JobRecord:
    """The job as clients see it: unfinished and silent for over stale_after means interrupted."""
    silent = now - job.heartbeat_at
    if job.finished or silent <= stale_after:
        return job
    error = (
        f"the process running this job ({job.owner}) stopped: no heartbeat for"
        f" {int(silent.total_seconds())} s (limit {int(stale_after.total_seconds())} s)."
        f" {interrupted_note(job.id)}"
    )
    return replace(job, state="interrupted", errors=(*job.errors, error), finished_at=job.heartbeat_at)


def interrupted_note(job_id: str) -> str:
    """What an interrupted job's report says (a version and its job's success are one transaction)."""
    return (
        "Nothing was stored: a version is written in the same transaction that marks its job"
        f" succeeded. Retry it with POST /v1/admin/jobs/{job_id}/retry on a server sharing the data"
        " directory that received the upload (it is kept there), or upload the batch again"
    )


def disk_full_note(job_id: str, error: StoreFull) -> str:
    """What a job that failed for a full disk reports."""
    return (
        f"disk full: the calibration store could not write the version ({error}); nothing was stored."
        f" Its upload is kept: retry it with POST /v1/admin/jobs/{job_id}/retry once space is freed"
    )


class JobCancelled(Exception):
    """Raised into a running job by its progress report once the service is stopping."""


class _Tracked:
    """A job of this process: its latest snapshot and what the store last received."""

    def __init__(self, job: JobRecord) -> None:
        self.job = job
        self.stored = job
        self.stored_at = self.attempted_at = time.monotonic()
        self.write_lock = threading.Lock()  # one write at a time, so writes land in order

    @property
    def dirty(self) -> bool:
        return self.job != self.stored


class JobProgress:
    """Handed to a running job so it can report progress without knowing the runner."""

    def __init__(self, runner: JobRunner, job_id: str) -> None:
        self._runner, self._id = runner, job_id

    def advance(self, count: int = 1) -> None:
        """Count ``count`` more instances done; raises ``JobCancelled`` when the service is stopping."""
        self._runner._change(self._id, lambda job: replace(job, done=job.done + count))
        if self._runner._stopping.is_set():
            raise JobCancelled(f"job {self._id}: the service is stopping")


JobFunction = Callable[[JobProgress], dict]


class JobRunner:
    """Runs jobs on ``workers`` threads; their state lives in ``store`` for every process."""

    def __init__(self, store: CalibrationStore, workers: int = 1, owner: str | None = None) -> None:
        self._store = store
        self._owner = owner or process_owner()
        self._pool = ThreadPoolExecutor(max_workers=workers, thread_name_prefix="calibration")
        self._tracked: dict[str, _Tracked] = {}
        self._lock = threading.Lock()
        self._stopping = threading.Event()
        self._stop = threading.Event()
        self._writer = threading.Thread(target=self._write_loop, name="job-writer", daemon=True)
        self._writer.start()

    def submit(
        self,
        kind: str,
        function: JobFunction,
        total: int = 0,
        job_id: str | None = None,
        audit: Sequence[NewAuditEntry] = (),
    ) -> JobRecord:
        """Store a queued job with the ``audit`` entries that accept it (one transaction), then
        queue it; raises Unavailable if the store cannot take them."""
        now = datetime.now(UTC)
        job = JobRecord(
            id=job_id or new_job_id(),
            kind=kind,
            owner=self._owner,
            created_at=now,
            heartbeat_at=now,
            total=total,
        )
        try:
            with disk_full_refused("the job's record"):
                self._store.create_job(job, audit)
        except StoreError as error:
            detail = f"the job could not be recorded, so it was not started: {error}"
            raise StoreUnreachable(detail) from error
        written(*audit)
        with self._lock:
            self._tracked[job.id] = _Tracked(job)
        try:
            self._pool.submit(self._run, job.id, function)
        except RuntimeError as error:  # the pool is shut down: the service is stopping
            note = "the service was stopping. " + interrupted_note(job.id)
            self._finish(job.id, "interrupted", errors=(note,))
            raise Unavailable("the service is stopping: retry the job, or upload the batch again") from error
        return job

    def get(self, job_id: str) -> JobRecord | None:
        """The stored job, whichever process runs it (None if unknown or pruned); one this process
        runs as it knows it, alive now, when the store has not taken its latest state (a store
        that cannot write, a full disk, would otherwise have it read interrupted)."""
        own = self._snapshot(job_id)
        try:
            job = self._store.get_job(job_id)
        except StoreError as error:
            if own is None:
                raise StoreUnreachable(f"the calibration store is unreachable: {error}") from error
            job = None
        if own is not None and (job is None or not job.finished):
            return replace(own, heartbeat_at=datetime.now(UTC))
        return None if job is None else reported(job, datetime.now(UTC))

    def _snapshot(self, job_id: str) -> JobRecord | None:
        with self._lock:
            entry = self._tracked.get(job_id)
            return None if entry is None else entry.job

    def shutdown(self) -> None:
        """Stop without waiting for jobs to finish: every queued or running job is marked
        interrupted in the store at once (its upload is kept for a retry), a running one stops
        at its next image; then what is left is written to the store."""
        self._stopping.set()
        self._pool.shutdown(wait=False, cancel_futures=True)
        unfinished = [entry.job for entry in self._entries() if not entry.job.finished]
        log.info("stopping calibration jobs: %d unfinished", len(unfinished))
        for job in unfinished:
            self._interrupt(job)
        started = time.monotonic()
        self._pool.shutdown(wait=True)
        log.info("calibration threads stopped in %.2f s", time.monotonic() - started)
        self._stop.set()
        self._writer.join()
        for entry in self._entries():
            self._write(entry)

    def _interrupt(self, job: JobRecord) -> None:
        """Mark a job interrupted, with one attempt at the store (the heartbeat covers a failure)."""
        scored = f"{job.done}/{job.total} instances scored"
        when = "before the job started" if job.state == "queued" else f"while the job was running ({scored})"
        error = f"the service stopped {when}. {interrupted_note(job.id)}"
        self._finish(job.id, "interrupted", attempts=1, errors=(error,))
        try:
            stored = self._store.get_job(job.id)
        except StoreError as failure:
            log.warning(
                "job %s (%s) could not be marked interrupted (%s); it will be reported interrupted"
                " once its heartbeat is %d s old",
                job.id,
                scored,
                failure,
                STALE_AFTER.total_seconds(),
            )
            return
        if stored is not None and stored.state != "interrupted":
            log.info("job %s %s before it could be interrupted", job.id, stored.state)
            return
        log.info(
            "job %s (%s, %s) marked interrupted; its upload is kept: retry it with"
            " POST /v1/admin/jobs/%s/retry",
            job.id,
            job.state,
            scored,
            job.id,
        )

    # -- running ----------------------------------------------------------------

    def _run(self, job_id: str, function: JobFunction) -> None:
        if self._stopping.is_set():  # interrupted before it started
            return
        self._prune()
        entry = self._change(job_id, lambda job: replace(job, state="running"))
        if entry is not None:
            self._write(entry)
        try:
            result = function(JobProgress(self, job_id))
        except JobCancelled:  # shutdown() marked it interrupted and writes what is left
            log.info("job %s stopped scoring: the service is stopping", job_id)
        except JobFinished as error:  # interrupted at shutdown, or a retry took it over elsewhere
            if self._stopping.is_set():
                log.info("job %s was interrupted before it could store its version", job_id)
            else:
                log.warning("job %s was finished elsewhere (%s); its work here was not stored", job_id, error)
            self._forget(job_id)
        except StoreFull as error:  # nothing committed; its upload is kept for a retry
            self._finish(job_id, "failed", errors=(disk_full_note(job_id, error),), result={RETRYABLE: True})
        except StoreUnavailable as error:  # nothing committed: had it, the job's row would refuse this write
            detail = f"the calibration store was unreachable ({error}); nothing was stored"
            self._finish(job_id, "failed", errors=(detail + ": upload the batch again",))
        except ServiceError as error:
            self._finish(job_id, "failed", errors=(error.detail, *error.errors))
        except Exception as error:  # a job must never take the worker down with it
            log.exception("calibration job %s failed", job_id)
            self._finish(job_id, "failed", errors=(f"internal error: {type(error).__name__}: {error}",))
        else:
            self._finish(job_id, "succeeded", result=result)

    def _finish(self, job_id: str, state: str, attempts: int = FINAL_WRITE_ATTEMPTS, **changes: Any) -> None:
        """Record the final state, then write it, retrying a few times."""
        entry = self._change(job_id, lambda job: _final(job, state, changes))
        if entry is None:  # not tracked, or finished already (e.g. interrupted by shutdown())
            return
        CALIBRATION_JOBS.labels(entry.job.state).inc()
        for attempt in range(attempts):
            if self._write(entry):
                return
            if attempt + 1 < attempts:
                time.sleep(RETRY_DELAY_S * 2**attempt)
        log.error("job %s: its final state is not stored yet; retrying in the background", job_id)

    def _prune(self) -> None:
        try:
            self._store.prune_jobs()
        except Exception as error:  # pruning is housekeeping: never fail a job over it
            log.warning("could not prune old jobs: %s", error)

    # -- the store ----------------------------------------------------------------

    def _entries(self) -> list[_Tracked]:
        with self._lock:
            return list(self._tracked.values())

    def _change(self, job_id: str, change: Callable[[JobRecord], JobRecord]) -> _Tracked | None:
        """Apply ``change`` to a tracked job's snapshot and return its entry; None when the job is
        not tracked or finished (a finished job never changes)."""
        with self._lock:
            entry = self._tracked.get(job_id)
            if entry is None or entry.job.finished:
                return None
            entry.job = change(entry.job)
            return entry

    def _write(self, entry: _Tracked) -> bool:
        """Send the latest snapshot (refreshing the heartbeat); False if the store failed."""
        with entry.write_lock:
            with self._lock:
                job = entry.job
            if job.finished and job == entry.stored:  # written already (by the other thread)
                return True
            entry.attempted_at = time.monotonic()
            try:
                self._store.update_job(job.id, **job.progress_fields())  # the store sets the heartbeat
            except JobFinished:  # completed with its version, or taken over by a retry
                self._forget(job.id)
                return True
            except JobNotFound:
                log.error("job %s: its row is gone from the store; no longer tracked", job.id)
                self._forget(job.id)
                return True
            except Exception as error:  # the store may be away for a moment: the job goes on
                log.warning("job %s: could not write it to the store: %s", job.id, error)
                return False
            entry.stored, entry.stored_at = job, entry.attempted_at
        if job.finished:
            self._forget(job.id)
        return True

    def _forget(self, job_id: str) -> None:
        with self._lock:
            self._tracked.pop(job_id, None)

    def _write_loop(self) -> None:
        while not self._stop.wait(_TICK_S):
            now = time.monotonic()
            for entry in self._entries():
                if now - entry.attempted_at < PROGRESS_WRITE_S:
                    continue
                if entry.dirty or now - entry.stored_at >= HEARTBEAT_S:
                    self._write(entry)


def new_job_id() -> str:
    return uuid.uuid4().hex


def _final(job: JobRecord, state: str, changes: dict[str, Any]) -> JobRecord:
    """The job in its final state; a result the store cannot hold fails the job instead."""
    finished_at = datetime.now(UTC)
    try:
        return replace(job, state=state, finished_at=finished_at, **changes)
    except (TypeError, ValueError) as error:
        log.error("job %s: cannot store its result: %s", job.id, error)
        errors = (f"internal error: the job's result cannot be stored: {error}",)
        return replace(job, state="failed", finished_at=finished_at, errors=errors)


# -- calibration jobs --------------------------------------------------------------


@dataclass(frozen=True)
class JobSettings:
    jobs_dir: Path
    intake: IntakeRules
    versions: VersionRules


class DetectorJobs:
    """What accepting and running background jobs over one detector's calibrations needs."""

    def __init__(
        self,
        store: CalibrationStore,
        detector: Detector,
        registry: CalibrationRegistry,
        runner: JobRunner,
        audit: AuditTrail,
        settings: JobSettings,
    ) -> None:
        self._store, self._detector, self._registry = store, detector, registry
        self._runner, self._audit, self._settings = runner, audit, settings
        self._intake = Intake(store, detector, registry.scores, settings.intake)


class CalibrationJobs(DetectorJobs):
    """Accepts, runs and retries calibration jobs for one detector and store."""

    def accept(
        self, workspace: UploadWorkspace, sha256: str, options: UploadOptions, operator: Operator
    ) -> JobRecord:
        """Take a received upload in and start its job, or refuse it (nothing is kept)."""
        folder = JobFolder.of(self._settings.jobs_dir, new_job_id())
        try:
            with disk_full_refused("the upload's files"):
                folder.adopt(workspace)
                batch = self._intake.take_in(folder.archive, sha256, options)
                fill_disk_point("job-request", self._settings.jobs_dir.parent)
                folder.save(_kept(options, operator, sha256, batch, folder))
            details = _accepted(folder.job_id, batch, options)
            accepted = self._audit.entry(operator, "upload", "accepted", reason=options.note, details=details)
            return self._submit(folder, batch, options, operator, accepted)
        except BaseException:
            folder.remove()
            workspace.remove()  # when it was not moved
            raise

    def retry(self, job_id: str, operator: Operator) -> JobRecord:
        """Run an interrupted job, or one failed for a full disk, again as a new job, from its
        kept upload."""
        job = self._retryable(job_id)
        old = JobFolder.of(self._settings.jobs_dir, job_id)
        if not old.exists():
            raise _not_kept(job, self._settings.jobs_dir)
        kept = old.load()
        options, original = UploadOptions.from_json(kept["request"]), Operator(**kept["operator"])
        named = self._intake.read(old.root / kept["batch_dir"], kept["sha256"], options.name)
        batch = self._intake.validate(named, options)  # refused before the job is taken over
        new = JobFolder.of(self._settings.jobs_dir, new_job_id())
        if not self._store.get_job(job_id).finished:  # reported interrupted: its process may live
            self._take_over(job, new.job_id)
        try:
            old.move_to(new)  # one rename wins: a job is retried once
        except FileNotFoundError as error:
            raise Conflict(f"job {job_id} was retried meanwhile") from error
        accepted = self._audit.entry(
            operator, "retry", "accepted", details={"job": job_id, "new_job": new.job_id}
        )
        try:
            return self._submit(new, batch.moved(old.root, new.root), options, original, accepted)
        except BaseException:
            new.move_to(old)  # not started (a store away or full): it can be retried again
            raise

    def _submit(
        self,
        folder: JobFolder,
        batch: ValidatedBatch,
        options: UploadOptions,
        operator: Operator,
        accepted: NewAuditEntry,
    ) -> JobRecord:
        """Start the job, its ``accepted`` entry stored with it."""

        def job(progress: JobProgress) -> dict[str, Any]:
            return self._job(folder, batch, options, operator, progress)

        count = batch.named.batch.count
        return self._runner.submit(JOB_KIND, job, count, job_id=folder.job_id, audit=(accepted,))

    def _job(
        self,
        folder: JobFolder,
        batch: ValidatedBatch,
        options: UploadOptions,
        operator: Operator,
        progress: JobProgress,
    ) -> dict[str, Any]:
        """Score the batch into a version (guardrails, store write, activation: one transaction)."""
        try:
            if batch.duplicate_of is None:  # a twin accepted beside it may have been stored since
                self._intake.duplicate_of(batch, options)  # 409 (the job fails) unless allowed
            outcome = create_version(
                self._store,
                self._detector,
                [batch],
                batch.parent,
                options,
                operator,
                self._settings.versions,
                self._audit,
                progress.advance,
                job_id=folder.job_id,
            )
        except (JobCancelled, JobFinished):  # interrupted: its upload is kept
            raise
        except BaseException as error:  # refused or failed: its upload goes, unless retryable
            if isinstance(error, ServiceError):
                details = {"job": folder.job_id, "detail": error.detail}
                self._audit.record(operator, "calibration", "failed", reason=options.note, details=details)
            elif isinstance(error, StoreError):  # failed by the store: audited once it is back
                details = {"job": folder.job_id, "detail": str(error)}
                self._audit.record_later(
                    operator, "calibration", "failed", reason=options.note, details=details
                )
            if not isinstance(error, StoreFull):  # a full disk's job is retried with its upload
                folder.remove()
            raise
        folder.remove()
        self._registry.refresh_now()
        return outcome.summary

    def _retryable(self, job_id: str) -> JobRecord:
        """The job to retry: an interrupted calibration job, or one failed for a full disk (404
        or 409 otherwise)."""
        job = self._runner.get(job_id)
        if job is None:
            raise NotFound(f"no job {job_id!r}: it never existed or was pruned")
        if job.kind != JOB_KIND:
            raise Conflict(
                f"job {job_id} is an {job.kind} job: only calibration jobs are retried; send its batch again"
            )
        if not retryable(job):
            raise Conflict(
                f"job {job_id} is {job.state}; only an interrupted job can be retried (or one failed for"
                " a full disk)"
            )
        return job

    def _take_over(self, job: JobRecord, new_id: str) -> None:
        """Mark a job reported interrupted finished (so its old process can no longer complete it);
        one that its stopping server marked interrupted already is left as it is (finished)."""
        try:
            self._store.update_job(
                job.id,
                state="interrupted",
                errors=job.errors,
                finished_at=datetime.now(UTC),
                result={**job.result, "retried_as": new_id},
            )
        except JobFinished as error:
            if error.state != "interrupted":
                raise Conflict(f"job {job.id} was retried or finished meanwhile: {error}") from error


def _kept(
    options: UploadOptions, operator: Operator, sha256: str, batch: ValidatedBatch, folder: JobFolder
) -> dict[str, Any]:
    """What is kept with an upload for a retry."""
    batch_dir = str(batch.named.batch.folder.relative_to(folder.root))
    return {
        "request": options.as_json(),
        "operator": asdict(operator),
        "sha256": sha256,
        "batch_dir": batch_dir,
    }


def _not_kept(job: JobRecord, jobs_dir: Path) -> Conflict:
    retried_as = job.result.get("retried_as")
    if retried_as:
        return Conflict(f"job {job.id} was retried already, as job {retried_as}")
    return Conflict(
        f"the upload of job {job.id} is not kept in this server's data directory"
        f" ({jobs_dir}): it was retried already (GET /v1/admin/audit says as"
        f" which job), or it is kept by the server that received it ({job.owner}); retry"
        " there, or upload the batch again"
    )


def _accepted(job_id: str, batch: ValidatedBatch, options: UploadOptions) -> dict[str, Any]:
    named = batch.named
    return {
        "job": job_id,
        "batch": named.name,
        "sha256": named.sha256,
        "instances": named.batch.count,
        "duplicates_dropped": batch.repeats_dropped,
        "rejected": len(batch.rejected),
        **({} if batch.duplicate_of is None else {"duplicate_of": batch.duplicate_of, "why": options.reason}),
    }
