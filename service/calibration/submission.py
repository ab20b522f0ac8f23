"""Calibration uploads as background jobs: accepted after every check that can refuse them,
run with their upload kept until they finish, and retried when a crash interrupted them."""

from __future__ import annotations

import logging
from dataclasses import asdict, dataclass
from datetime import UTC, datetime
from pathlib import Path
from typing import Any

from calibration_store import CalibrationStore, JobFinished, JobRecord, ScoreTable
from service.calibration.archive import ArchiveLimits, DiskBudget
from service.calibration.calibrate import CalibrationOptions, check_parent, create_calibration
from service.calibration.coco import NamedBatch
from service.calibration.intake import PreparedBatch, prepare_batch
from service.calibration.jobs import JobProgress, JobRunner, new_job_id
from service.calibration.registry import CalibrationRegistry
from service.calibration.stratification import GROUP, parse_stratify
from service.calibration.uploads import JobFolder, UploadWorkspace, batch_name, reload_batch, validate_upload
from service.conformal.strata import DifficultySpec
from service.detector.session import Detector
from service.errors import Conflict, InvalidInput, NotFound, ServiceError
from service.runtime.audit_trail import AuditTrail, Operator

log = logging.getLogger(__name__)
JOB_KIND = "calibration"


@dataclass(frozen=True)
class UploadRequest:
    """What the operator asked for with an upload (kept with it, for a retry)."""

    name: str | None = None
    note: str = ""
    append_to: int | None = None
    activate: bool = False
    force: bool = False
    reason: str = ""
    dedupe: bool = False
    max_rejected_share: float | None = None
    stratify: str | None = None  # None: difficulty strata when the scores carry heatmap features

    def __post_init__(self) -> None:
        if self.stratify is not None:
            parse_stratify(self.stratify)  # refused now (422), not when the job runs
        if self.force and not self.reason.strip():
            raise InvalidInput("force needs a reason (force=true&reason=..., or --force --reason ...):"
                               " say why the guardrails may be overridden")  # fmt: skip
        if self.force and not self.activate:
            raise InvalidInput("force only applies when activating (activate=true, or --activate)")

    def rejected_share(self, default: float) -> float:
        return default if self.max_rejected_share is None else self.max_rejected_share

    def options(
        self, operator: Operator, default_share: float, min_instances: int, difficulty: DifficultySpec
    ) -> CalibrationOptions:
        """The calibration this request asks for (``default_share`` when it names none)."""
        return CalibrationOptions(
            operator=operator,
            note=self.note,
            append_to=self.append_to,
            activate=self.activate,
            force=self.force,
            reason=self.reason,
            max_rejected_share=self.rejected_share(default_share),
            min_instances=min_instances,
            stratify=None if self.stratify is None else parse_stratify(self.stratify),
            difficulty=difficulty,
        )


@dataclass(frozen=True)
class SubmissionSettings:
    jobs_dir: Path
    limits: ArchiveLimits
    max_image_pixels: int
    min_instances: int
    max_rejected_share: float
    disk: DiskBudget | None = None
    difficulty: DifficultySpec = DifficultySpec()


class DetectorJobs:
    """What accepting and running background jobs over one detector's calibrations needs."""

    def __init__(
        self,
        store: CalibrationStore,
        detector: Detector,
        registry: CalibrationRegistry,
        runner: JobRunner,
        audit: AuditTrail,
        settings: SubmissionSettings,
    ) -> None:
        self._store, self._detector, self._registry = store, detector, registry
        self._runner, self._audit, self._settings = runner, audit, settings


class CalibrationJobs(DetectorJobs):
    """Accepts, runs and retries calibration jobs for one detector and store."""

    def accept(
        self, workspace: UploadWorkspace, sha256: str, request: UploadRequest, operator: Operator
    ) -> JobRecord:
        """Validate a received upload and start its job, or refuse it (nothing is kept)."""
        folder = JobFolder.of(self._settings.jobs_dir, new_job_id())
        folder.adopt(workspace)
        try:
            settings = self._settings
            named = validate_upload(folder, batch_name(request.name, sha256), sha256,
                                    self._detector.manifest, settings.limits, settings.disk)  # fmt: skip
            prepared = self._prepare(named, request)
            folder.save({"request": asdict(request), "operator": asdict(operator), "sha256": sha256,
                         "batch_dir": str(named.batch.folder.relative_to(folder.root))})  # fmt: skip
            job = self._submit(folder, prepared, request, operator)
        except BaseException:
            folder.remove()
            raise
        details = _accepted(job, prepared)
        self._audit.record(operator, "upload", "accepted", reason=request.note, details=details)
        return job

    def retry(self, job_id: str, operator: Operator) -> JobRecord:
        """Run an interrupted job again as a new job, from its kept upload."""
        job = self._runner.get(job_id)
        if job is None:
            raise NotFound(f"no job {job_id!r}: it never existed or was pruned")
        if job.kind != JOB_KIND:
            raise Conflict(f"job {job_id} is an {job.kind} job: only calibration jobs are retried; send its"
                           " batch again")  # fmt: skip
        if job.state != "interrupted":
            raise Conflict(f"job {job_id} is {job.state}; only an interrupted job can be retried")
        old = JobFolder.of(self._settings.jobs_dir, job_id)
        if not old.exists():
            retried_as = job.result.get("retried_as")
            raise Conflict(
                f"job {job_id} was retried already, as job {retried_as}" if retried_as else
                f"the upload of job {job_id} is not kept in this server's data directory"
                f" ({self._settings.jobs_dir}): it was retried already (GET /v1/admin/audit says as"
                f" which job), or it is kept by the server that received it ({job.owner}); retry"
                " there, or upload the batch again"
            )  # fmt: skip
        kept = old.load()
        request, original = UploadRequest(**kept["request"]), Operator(**kept["operator"])
        named = reload_batch(old, kept["batch_dir"], batch_name(request.name, kept["sha256"]), kept["sha256"],
                             self._detector.manifest)  # fmt: skip
        self._prepare(named, request)  # refuse before taking the job over
        new = JobFolder.of(self._settings.jobs_dir, new_job_id())
        if self._store.get_job(job_id).state != "interrupted":  # only reported so: its process may live
            self._take_over(job, new.job_id)
        try:
            old.move_to(new)  # one rename wins: a job is retried once
        except FileNotFoundError as error:
            raise Conflict(f"job {job_id} was retried meanwhile") from error
        named = reload_batch(new, kept["batch_dir"], named.name, named.sha256, self._detector.manifest)
        retried = self._submit(new, self._prepare(named, request), request, original)
        self._audit.record(operator, "retry", "accepted", details={"job": job_id, "new_job": retried.id})
        return retried

    def _take_over(self, job: JobRecord, new_id: str) -> None:
        """Mark a job reported interrupted finished (so its old process can no longer complete it);
        one that its stopping server marked interrupted already is left as it is (finished)."""
        try:
            self._store.update_job(
                job.id, state="interrupted", errors=job.errors, finished_at=datetime.now(UTC),
                result={**job.result, "retried_as": new_id},
            )  # fmt: skip
        except JobFinished as error:
            if error.state != "interrupted":
                raise Conflict(f"job {job.id} was retried or finished meanwhile: {error}") from error

    def _prepare(self, named: NamedBatch, request: UploadRequest) -> PreparedBatch:
        parent = parent_table = None
        if request.append_to is not None:
            parent = check_parent(self._store, self._detector, request.append_to)
            parent_table = self._registry.scores(request.append_to)
        _check_group_labels(named, parent_table, request)
        share = request.rejected_share(self._settings.max_rejected_share)
        return prepare_batch(named, parent, parent_table, dedupe=request.dedupe, max_rejected_share=share)

    def _options(self, request: UploadRequest, operator: Operator) -> CalibrationOptions:
        settings = self._settings
        share, minimum = settings.max_rejected_share, settings.min_instances
        return request.options(operator, share, minimum, settings.difficulty)

    def _submit(
        self, folder: JobFolder, prepared: PreparedBatch, request: UploadRequest, operator: Operator
    ) -> JobRecord:
        options = self._options(request, operator)

        def run(progress: JobProgress) -> dict[str, Any]:
            try:
                outcome = create_calibration(
                    self._store, self._detector, [prepared], options, self._settings.max_image_pixels,
                    self._audit, progress.advance, job_id=folder.job_id,
                )  # fmt: skip
            except ServiceError as error:
                self._audit.record(operator, "calibration", "failed", reason=request.note,
                                   details={"job": folder.job_id, "detail": error.detail})  # fmt: skip
                folder.remove()
                raise
            folder.remove()
            self._registry.refresh_now()
            return outcome.summary

        return self._runner.submit(JOB_KIND, run, prepared.named.batch.count, job_id=folder.job_id)


def _check_group_labels(named: NamedBatch, parent: ScoreTable | None, request: UploadRequest) -> None:
    """stratify=group is refused at once (422) when no instance carries a group label."""
    if request.stratify is None or GROUP not in parse_stratify(request.stratify):
        return
    inherited = parent is not None and any(block.has_groups for block in parent.objects)
    if not inherited and not any(instance.group for instance in named.batch.instances):
        raise InvalidInput('stratify=group needs group labels, and no annotation of the batch carries one:'
                           ' add "group": "<label>" (a camera, a site) to the COCO annotations')  # fmt: skip


def _accepted(job: JobRecord, prepared: PreparedBatch) -> dict[str, Any]:
    named = prepared.named
    return {
        "job": job.id,
        "batch": named.name,
        "sha256": named.sha256,
        "instances": named.batch.count,
        "duplicates_dropped": prepared.repeats_dropped,
        "rejected": len(prepared.rejected),
    }
