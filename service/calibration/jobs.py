"""Calibration uploads as jobs of ``infra.job_engine``: accepted after the intake, run as one step
that turns the batch into a version (in the transaction that marks the job succeeded), retried
from their kept upload (``<data>/jobs/<job id>``) after a crash or a full disk.
"""

from __future__ import annotations

import logging
from dataclasses import asdict, dataclass
from datetime import UTC, datetime
from functools import partial
from pathlib import Path
from typing import Any

from calibration_store import CalibrationStore, JobFinished, JobRecord, NewAuditEntry, StoreError, StoreFull
from service.calibration.intake import Intake, IntakeRules, UploadOptions, ValidatedBatch
from service.calibration.registry import CalibrationRegistry
from service.calibration.uploads import JobFolder, UploadWorkspace
from service.calibration.versions import VersionRules, create_version
from service.detector.session import Detector
from service.errors import Conflict, NotFound, ServiceError, disk_full_refused
from service.infra.audit_trail import AuditTrail, Operator
from service.infra.job_engine import JobCancelled, JobProgress, JobRunner, new_job_id, retryable
from service.infra.processes import process_owner

log = logging.getLogger(__name__)
JOB_KIND = "calibration"


@dataclass(frozen=True)
class JobSettings:
    jobs_dir: Path
    intake: IntakeRules
    versions: VersionRules


class DetectorJobs:
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
                named = self._intake.unpack(folder.archive, sha256, options.name)
                batch = self._intake.validate(named, options)
                folder.save(_kept(options, operator, sha256, batch, folder))
            details = _accepted(folder.job_id, batch, options)
            accepted = self._audit.entry(operator, "upload", "accepted", reason=options.note, details=details)
            return self._submit(folder, batch, options, operator, accepted)
        except BaseException:
            folder.remove()
            workspace.remove()  # when it was not moved
            raise

    def take_over(self, job: JobRecord) -> bool:
        """Retry a job whose process stopped when its upload is kept here (False: it is not)."""
        if not JobFolder.of(self._settings.jobs_dir, job.id).exists():
            return False
        self.retry(job.id, Operator("takeover", client=process_owner()))
        return True

    def retry(self, job_id: str, operator: Operator) -> JobRecord:
        """Run an interrupted job, or one failed for a full disk, again as a new job from its upload."""
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
        details = {"job": job_id, "new_job": new.job_id}
        accepted = self._audit.entry(operator, "retry", "accepted", details=details)
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
        job = partial(self._job, folder, batch, options, operator)
        return self._runner.submit(
            JOB_KIND, job, batch.named.batch.count, job_id=folder.job_id, audit=(accepted,)
        )

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
            store, detector, rules, audit = self._store, self._detector, self._settings.versions, self._audit
            parent, advance = batch.parent, progress.advance
            outcome = create_version(
                store, detector, [batch], parent, options, operator, rules, audit, advance, folder.job_id
            )
        except (JobCancelled, JobFinished):  # interrupted: its upload is kept
            raise
        except BaseException as error:  # refused or failed: its upload goes, unless retryable
            note = options.note
            if isinstance(error, ServiceError):
                twin = {k: v for k, v in error.extensions.items() if k == "duplicate_of"}
                details = {"job": folder.job_id, "detail": error.detail, **twin}
                self._audit.record(operator, "calibration", "failed", reason=note, details=details)
            elif isinstance(error, StoreError):  # failed by the store: audited once it is back
                details = {"job": folder.job_id, "detail": str(error)}
                self._audit.record_later(operator, "calibration", "failed", reason=note, details=details)
            if not isinstance(error, StoreFull):  # a full disk's job is retried with its upload
                folder.remove()
            raise
        folder.remove()
        self._registry.refresh_now()
        return outcome.summary

    def _retryable(self, job_id: str) -> JobRecord:
        """The job to retry: an interrupted calibration job, or one failed for a full disk."""
        if (job := self._runner.get(job_id)) is None:
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
        """Mark a job reported interrupted finished, so its old process can no longer complete it."""
        now, result = datetime.now(UTC), {**job.result, "retried_as": new_id}
        try:
            self._store.update_job(
                job.id, state="interrupted", errors=job.errors, finished_at=now, result=result
            )
        except JobFinished as error:
            if error.state != "interrupted":
                raise Conflict(f"job {job.id} was retried or finished meanwhile: {error}") from error


def _kept(
    options: UploadOptions, operator: Operator, sha256: str, batch: ValidatedBatch, folder: JobFolder
) -> dict[str, Any]:
    batch_dir = str(batch.named.batch.folder.relative_to(folder.root))
    return dict(request=options.as_json(), operator=asdict(operator), sha256=sha256, batch_dir=batch_dir)


def _not_kept(job: JobRecord, jobs_dir: Path) -> Conflict:
    retried_as = job.result.get("retried_as")
    if retried_as:
        return Conflict(f"job {job.id} was retried already, as job {retried_as}")
    return Conflict(
        f"the upload of job {job.id} is not kept in this server's data directory ({jobs_dir}): it was"
        f" retried already (GET /v1/admin/audit says as which job), or it is kept by the server that"
        f" received it ({job.owner}); retry there, or upload the batch again"
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
