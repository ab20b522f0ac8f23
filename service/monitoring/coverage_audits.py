"""Coverage audits as background jobs: a labeled batch scored against a version's thresholds, the
report stored and published as Prometheus gauges (never changes a calibration; not retried).
"""

from __future__ import annotations

import logging
import math
import os
import threading
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np
from prometheus_client import Gauge

from calibration_store import (
    CoverageAudit,
    JobCompletion,
    JobRecord,
    NewAuditEntry,
    NewCoverageAudit,
    StoreError,
)
from service.calibration.coco import NamedBatch
from service.calibration.intake import Parent, ValidatedBatch, check_batch, check_rejected_share
from service.calibration.jobs import DetectorJobs
from service.calibration.scoring import ScoreAccumulator, score_batch
from service.calibration.uploads import UploadWorkspace
from service.errors import Conflict, InvalidInput
from service.infra.audit_trail import Operator
from service.infra.job_engine import JobProgress, new_job_id
from service.infra.metrics import (
    AUDIT_BAND_HIGH,
    AUDIT_BAND_LOW,
    AUDIT_COVERAGE,
    AUDIT_FLAGGED,
    AUDIT_LATEST,
    MULTIPROCESS_ENV,
)
from service.monitoring.audit_report import DEFAULT_EPSILONS, ThresholdLookup, audit_report

log = logging.getLogger(__name__)
JOB_KIND = "audit"
MAX_EPSILONS = 10


@dataclass(frozen=True)
class AuditRequest:
    version: int | None = None  # None: the active version
    epsilons: tuple[float, ...] = DEFAULT_EPSILONS
    name: str | None = None
    note: str = ""
    dedupe: bool = False
    max_rejected_share: float | None = None

    def __post_init__(self) -> None:
        epsilons = tuple(sorted(set(self.epsilons)))
        if not epsilons or len(epsilons) > MAX_EPSILONS or not all(0 < e < 1 for e in epsilons):
            raise InvalidInput(
                f"epsilon must be 1 to {MAX_EPSILONS} values in (0, 1), e.g. epsilon=0.05&epsilon=0.1"
            )
        object.__setattr__(self, "epsilons", epsilons)


class CoverageAudits(DetectorJobs):
    def accept(
        self, workspace: UploadWorkspace, sha256: str, request: AuditRequest, operator: Operator
    ) -> JobRecord:
        """Validate a received batch and start its audit, or refuse it (the upload is removed)."""
        job_id = new_job_id()
        try:
            version = self._registry.resolve(request.version)  # 404, 409, 503
            named = self._intake.unpack(workspace.archive, sha256, request.name)
            prepared = self._prepare(named, version, request)
            details = {"job": job_id, "version": version, "batch": named.name, "sha256": sha256}
            details |= {"instances": named.batch.count, "epsilons": list(request.epsilons)}
            accepted = self._audit.entry(
                operator, "audit", "accepted", version=version, reason=request.note, details=details
            )
            return self._submit(job_id, workspace, prepared, version, request, operator, accepted)
        except BaseException:
            workspace.remove()
            raise

    def publish_latest(self) -> None:
        latest = self._newest()
        if latest is not None:
            publish_audit(latest.id, latest.report)

    def follow_latest(self, interval: float, stop: threading.Event) -> None:
        """Publish the newest audit of any process every ``interval`` seconds until ``stop``."""

        def follow() -> None:
            while not stop.wait(interval):
                latest = self._newest()
                if latest is not None and latest.id != published_id():
                    publish_audit(latest.id, latest.report, self._newest(before=latest.id))

        threading.Thread(target=follow, name="audit-follower", daemon=True).start()

    def _newest(self, before: int | None = None) -> CoverageAudit | None:
        """The newest audit of the served model (before ``before``); None if none or the store failed."""
        try:
            audits = self._store.coverage_audits(self._detector.model_hash, before=before, limit=1)
        except StoreError as error:
            log.warning("could not read the coverage audits for the metrics: %s", error)
            return None
        return audits[0] if audits else None

    def _prepare(self, named: NamedBatch, version: int, request: AuditRequest) -> ValidatedBatch:
        """Refuse instances the audited version was calibrated with (they would flatter it)."""
        info = self._store.get_version(self._detector.model_hash, version)
        audited = Parent(info, self._registry.scores(version))
        try:
            return check_batch(named, audited, dedupe=request.dedupe, max_rejected_share=self._share(request))
        except Conflict as error:
            raise Conflict(
                f"an audit needs instances that version {version} was not calibrated with: {error.detail}",
                errors=error.errors,
                extensions=error.extensions,
            ) from error

    def _share(self, request: AuditRequest) -> float:
        share = request.max_rejected_share
        return self._settings.intake.max_rejected_share if share is None else share

    def _submit(
        self,
        job_id: str,
        workspace: UploadWorkspace,
        prepared: ValidatedBatch,
        version: int,
        request: AuditRequest,
        operator: Operator,
        accepted: NewAuditEntry,
    ) -> JobRecord:
        def run(progress: JobProgress) -> dict[str, Any]:
            try:
                report = self._measure(prepared, version, request, progress)
                instances, flagged = report["instances"], len(report["flagged"])
                summary = {
                    "version": version,
                    "passed": report["passed"],
                    "flagged": flagged,
                    "instances": instances,
                }
                new = NewCoverageAudit(
                    model_hash=self._detector.model_hash,
                    version=version,
                    who=operator.name,
                    batch_sha256=prepared.named.sha256,
                    n_instances=instances,
                    report=report,
                )
                stored = self._store.create_coverage_audit(new, job=JobCompletion(job_id, summary))
            finally:
                workspace.remove()
            publish_audit(stored.id, stored.report, self._newest(before=stored.id))
            outcome = "passed" if report["passed"] else "failed"
            details = {"job": job_id, "audit": stored.id, "flagged": summary["flagged"]}
            self._audit.record(operator, "audit", outcome, version=version, details=details)
            return {**summary, "audit": stored.id}

        count = prepared.named.batch.count
        return self._runner.submit(JOB_KIND, run, count, job_id=job_id, audit=(accepted,))

    def _measure(
        self, prepared: ValidatedBatch, version: int, request: AuditRequest, progress: JobProgress
    ) -> dict[str, Any]:
        named = prepared.named
        accumulator = ScoreAccumulator()
        pixels = self._settings.versions.max_image_pixels
        rejected = score_batch(named.batch, named.name, self._detector, accumulator, pixels, progress.advance)
        check_rejected_share([*prepared.rejected, *rejected], prepared.annotations, self._share(request))
        if accumulator.count == 0:
            raise InvalidInput("no instance of the batch could be scored: every image was left out")
        lookup = self._lookup(version)
        report = audit_report(accumulator.table(), self._detector.manifest, lookup, request.epsilons, version)
        rejections = [r.describe() for r in (*prepared.rejected, *rejected)]
        return {
            **report,
            "batch": {
                "name": named.name,
                "sha256": named.sha256,
                "note": request.note,
                "annotations": prepared.annotations,
                "rejected": len(rejections),
                "rejections": rejections[:20],
                "duplicates_dropped": prepared.repeats_dropped,
            },
        }

    def _lookup(self, version: int) -> ThresholdLookup:
        def thresholds(kind: str, scope: str, epsilon: float) -> tuple[np.ndarray, Sequence[int]]:
            found = self._registry.thresholds(version, kind, scope, epsilon, None)
            return found.values, [guarantee.n for guarantee in found.guarantees]

        return thresholds


def publish_audit(audit_id: int, report: dict[str, Any], previous: CoverageAudit | None = None) -> None:
    """Replace the audit gauges with this audit's, hiding the ``previous`` audit's."""
    samples = _audit_samples(audit_id, report)
    stale = set() if previous is None else set(_audit_samples(previous.id, previous.report))
    with _PUBLISHED_LOCK:
        for gauge, labels in (_PUBLISHED.keys() | stale) - samples.keys():
            _forget(gauge, labels)
        for (gauge, labels), value in samples.items():
            gauge.labels(*labels).set(value)
        _PUBLISHED.clear()
        _PUBLISHED.update(samples)


_PUBLISHED: dict[tuple[Gauge, tuple[str, ...]], float] = {}  # the samples this process shows
_PUBLISHED_LOCK = threading.Lock()


def published_id() -> int | None:
    """The id of the audit this process's gauges show (None: none)."""
    with _PUBLISHED_LOCK:
        return next((int(value) for (gauge, _), value in _PUBLISHED.items() if gauge is AUDIT_LATEST), None)


def _audit_samples(audit_id: int, report: dict[str, Any]) -> dict[tuple[Gauge, tuple[str, ...]], float]:
    samples = {(AUDIT_LATEST, (str(report.get("version", "")),)): float(audit_id)}
    for section in report.get("sections", []):
        where = (section["nonconformity"], f"{section['epsilon']:g}", section["scope"])
        figures = [("", "", section["overall"])]
        figures += [(f["object"], "", f) for f in section["objects"]]
        figures += [(f["object"], f["keypoint"], f) for f in section["keypoints"]]
        for obj, keypoint, figure in figures:
            if figure.get("coverage") is None:
                continue
            labels = (obj, keypoint, *where)
            samples[(AUDIT_COVERAGE, labels)] = figure["coverage"]
            samples[(AUDIT_BAND_LOW, labels)] = figure["band"][0]
            samples[(AUDIT_BAND_HIGH, labels)] = figure["band"][1]
            samples[(AUDIT_FLAGGED, labels)] = 1.0 if figure.get("flagged") else 0.0
    return samples


def _forget(gauge: Gauge, labels: tuple[str, ...]) -> None:
    """Drop an older sample (with several workers a NaN hides the others' old value)."""
    if os.environ.get(MULTIPROCESS_ENV):
        gauge.labels(*labels).set(math.nan)
    else:
        gauge.remove(*labels)
