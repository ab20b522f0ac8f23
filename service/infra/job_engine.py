"""The job engine: background jobs on this process's worker threads (``JobRunner``), their state in
the store's job table, so that any process of any replica answers for any job.

Progress is written by one writer thread (at most every PROGRESS_WRITE_S, a heartbeat at least
every HEARTBEAT_S). An unfinished job silent for over STALE_AFTER is reported interrupted (a job's
result is written in the transaction that marks it succeeded, so it stored nothing) and offered to
the takeover of its kind; one nobody took over within TAKEOVER_GRACE is stored interrupted. At
shutdown unfinished jobs are marked interrupted at once; a running one stops at its next progress
report (``JobCancelled``).
"""

from __future__ import annotations

import logging
import threading
import time
import uuid
from collections.abc import Callable, Sequence
from concurrent.futures import ThreadPoolExecutor
from dataclasses import replace
from datetime import UTC, datetime, timedelta
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
from service.errors import ServiceError, StoreUnreachable, Unavailable, disk_full_refused
from service.infra.audit_trail import written
from service.infra.metrics import CALIBRATION_JOBS
from service.infra.processes import process_owner

log = logging.getLogger(__name__)

#: progress reaches the store at most this often per job (plus the final state)
PROGRESS_WRITE_S = 1.0
#: an unfinished job of a live process is rewritten at least this often
HEARTBEAT_S = 10.0
#: an unfinished job silent for longer is reported failed (its process stopped)
STALE_AFTER = timedelta(seconds=60)
#: how often the writer thread looks for stale jobs of other processes
SWEEP_S = HEARTBEAT_S
#: how long past STALE_AFTER a stale job waits for a replica that can take it over
TAKEOVER_GRACE = STALE_AFTER
#: attempts at writing a job's final state before leaving it to the writer thread
FINAL_WRITE_ATTEMPTS = 4
RETRY_DELAY_S = 0.25
_TICK_S = 0.25


def reported(job: JobRecord, now: datetime) -> JobRecord:
    """The job as clients see it: unfinished and silent for over STALE_AFTER is interrupted."""
    silent = now - job.heartbeat_at
    if job.finished or silent <= STALE_AFTER:
        return job
    error = (
        f"the process running this job ({job.owner}) stopped: no heartbeat for"
        f" {int(silent.total_seconds())} s (limit {int(STALE_AFTER.total_seconds())} s)."
        f" {interrupted_note(job.id)}"
    )
    return replace(job, state="interrupted", errors=(*job.errors, error), finished_at=job.heartbeat_at)


def interrupted_note(job_id: str) -> str:
    """What an interrupted job's report says."""
    return (
        "Nothing was stored: a version is written in the same transaction that marks its job"
        f" succeeded. Retry it with POST /v1/admin/jobs/{job_id}/retry on a server sharing the data"
        " directory that received the upload (it is kept there), or upload the batch again"
    )


def disk_full_note(job_id: str, error: StoreFull) -> str:
    return (
        f"disk full: the calibration store could not write the version ({error}); nothing was stored."
        f" Its upload is kept: retry it with POST /v1/admin/jobs/{job_id}/retry once space is freed"
    )


#: in a failed job's result: its input is kept, and it can be retried (it failed for a full disk)
RETRYABLE = "retryable"


def retryable(job: JobRecord) -> bool:
    """Whether a job can be retried from its kept input: interrupted, or failed for a full disk."""
    return job.state == "interrupted" or (job.state == "failed" and job.result.get(RETRYABLE) is True)


class JobCancelled(Exception):
    """Raised into a running job by its progress report once the service is stopping."""


class _Tracked:
    """A job of this process: its latest snapshot and what the store last received."""

    def __init__(self, job: JobRecord) -> None:
        self.job = self.stored = job
        self.stored_at = self.attempted_at = time.monotonic()
        self.write_lock = threading.Lock()  # one write at a time, so writes land in order


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
#: runs a stale job of another process again, here (True), or says this process cannot read its input
Takeover = Callable[[JobRecord], bool]


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
        self._takeovers: dict[str, Takeover | None] = {}
        self._swept_at = -SWEEP_S
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
        """Store a queued job with the ``audit`` entries that accept it (one transaction), and queue it."""
        now = datetime.now(UTC)
        job = JobRecord(
            job_id or new_job_id(), kind, self._owner, created_at=now, heartbeat_at=now, total=total
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

    def on_stale(self, kind: str, take_over: Takeover | None) -> None:
        """Look after stale jobs of ``kind`` with ``take_over`` (None: no process can)."""
        with self._lock:
            self._takeovers[kind] = take_over

    def get(self, job_id: str) -> JobRecord | None:
        """The stored job, whichever process runs it (None if unknown or pruned); one this process runs
        as it knows it, alive now, when the store lacks its latest state."""
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
        """Stop without waiting for jobs: unfinished ones are marked interrupted at once."""
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
            stale = int(STALE_AFTER.total_seconds())
            log.warning(
                f"job {job.id} ({scored}) could not be marked interrupted ({failure}); it will be reported"
                f" interrupted once its heartbeat is {stale} s old"
            )
            return
        if stored is not None and stored.state != "interrupted":
            log.info("job %s %s before it could be interrupted", job.id, stored.state)
            return
        log.info(
            f"job {job.id} ({job.state}, {scored}) marked interrupted; its upload is kept: retry it with"
            f" POST /v1/admin/jobs/{job.id}/retry"
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
        """Apply ``change`` to a tracked, unfinished job's snapshot and return its entry, else None."""
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
                due = entry.job != entry.stored or now - entry.stored_at >= HEARTBEAT_S
                if due and now - entry.attempted_at >= PROGRESS_WRITE_S:
                    self._write(entry)
            if now - self._swept_at >= SWEEP_S:
                self._sweep()

    # -- stale jobs of stopped processes --------------------------------------------

    def _sweep(self) -> None:
        """Offer stale jobs to their kind's takeover; store interrupted those nobody took over."""
        with self._lock:
            takeovers = dict(self._takeovers)
        if not takeovers or self._stopping.is_set():  # a stopping process starts no job
            return
        self._swept_at = time.monotonic()
        now = datetime.now(UTC)
        try:
            stale = self._store.stale_jobs(now - STALE_AFTER)
        except StoreError as error:
            log.warning("could not look for stale jobs: %s", error)
            return
        for job in stale:
            if job.kind not in takeovers or self._snapshot(job.id) is not None:
                continue
            take_over = takeovers[job.kind]
            if take_over is not None and self._took_over(take_over, job):
                continue
            if take_over is None or now - job.heartbeat_at > STALE_AFTER + TAKEOVER_GRACE:
                self._store_interrupted(job, now, takeover_possible=take_over is not None)

    def _took_over(self, take_over: Takeover, job: JobRecord) -> bool:
        try:
            taken = take_over(job)
        except Exception as error:  # e.g. taken over by another process meanwhile
            log.warning("job %s (%s) of stopped process %s not taken over: %s", *_named(job), error)
            return False
        if taken:
            log.info("job %s (%s) of stopped process %s taken over", *_named(job))
        return taken

    def _store_interrupted(self, job: JobRecord, now: datetime, takeover_possible: bool) -> None:
        """Store a stale job as it is reported, interrupted, with why nobody took it over."""
        shown = reported(job, now)
        nobody = (
            f"No server that can read its upload took it over within {int(TAKEOVER_GRACE.total_seconds())} s"
            " (its upload is not readable here)"
            if takeover_possible
            else "A job of this kind is not taken over by another process"
        )
        errors = (*shown.errors, f"{nobody}: upload the batch again.")
        try:
            self._store.update_job(job.id, state="interrupted", errors=errors, finished_at=shown.finished_at)
        except JobFinished:  # taken over, or finished, meanwhile
            return
        except StoreError as error:
            log.warning(
                "job %s (%s) of stopped process %s could not be stored interrupted: %s", *_named(job), error
            )
            return
        log.info("job %s (%s) of stopped process %s stored interrupted: nobody took it over", *_named(job))


def _named(job: JobRecord) -> tuple[str, str, str]:
    return job.id, job.kind, job.owner


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
