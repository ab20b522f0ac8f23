"""Turn stored calibration versions into the admin API's response bodies."""

from __future__ import annotations

import math
from dataclasses import asdict

from calibration_store import Activation, AuditEntry, CoverageAudit, JobRecord, VersionInfo
from service.api.admin.admin_schemas import (
    ActivationOut,
    AuditEntryOut,
    AuditList,
    AuditOut,
    AuditPage,
    AuditReportOut,
    AuditSummaryOut,
    ComparisonOut,
    DriftOut,
    HistoryPointOut,
    JobOut,
    KeypointDriftOut,
    KindSizesOut,
    ObjectDriftOut,
    SourceBatchOut,
    ThresholdRow,
    VersionDetail,
    VersionSummary,
)
from service.calibration.guardrails import Comparison
from service.calibration.registry import CalibrationRegistry
from service.conformal import NONCONFORMITY_SCORES
from service.detector.manifest import Manifest
from service.monitoring.drift_monitor import DriftReport

REPORTED_EPSILONS = (0.05, 0.1, 0.2)


def summarize(info: VersionInfo, active: int | None) -> VersionSummary:
    return VersionSummary(
        version=info.number,
        created_at=info.created_at,
        author=info.author,
        note=info.note,
        parent_version=info.parent_version,
        instances=info.n_instances,
        objects=dict(info.object_counts),
        source_batches=[SourceBatchOut(**b.as_dict()) for b in info.source_batches],
        active=info.number == active,
    )


def _finite_or_none(value: float) -> float | None:
    return float(value) if math.isfinite(value) else None


def describe(
    info: VersionInfo, active: int | None, registry: CalibrationRegistry, manifest: Manifest
) -> VersionDetail:
    rows = []
    for kind in NONCONFORMITY_SCORES:
        for epsilon in REPORTED_EPSILONS:
            per_keypoint = registry.thresholds(info.number, kind, "keypoint", epsilon, None)
            per_object = registry.thresholds(info.number, kind, "object", epsilon, None)
            rows.append(
                ThresholdRow(
                    nonconformity=kind,
                    epsilon=epsilon,
                    keypoint={
                        k.name: _finite_or_none(per_keypoint.values[k.index]) for k in manifest.keypoints
                    },
                    object={
                        o.name: _finite_or_none(per_object.values[o.keypoints[0]]) for o in manifest.objects
                    },
                )
            )
    unusable_reason = registry.incompatibility(info.number)
    return VersionDetail(
        **summarize(info, active).model_dump(),
        normalization=dict(info.normalization),
        usable=unusable_reason is None,
        unusable_reason=unusable_reason,
        labeled_per_keypoint={k.name: per_keypoint.guarantees[k.index].n for k in manifest.keypoints},
        complete_per_object={o.name: per_object.guarantees[o.keypoints[0]].n for o in manifest.objects},
        thresholds=rows,
        strata=None if info.strata is None else dict(info.strata),
    )


def activation_out(entry: Activation) -> ActivationOut:
    return ActivationOut.model_validate(entry, from_attributes=True)


def job_out(job: JobRecord) -> JobOut:
    return JobOut.model_validate(job, from_attributes=True)


def comparison_out(comparison: Comparison) -> ComparisonOut:
    return ComparisonOut.model_validate(comparison.as_dict())


def audit_page(entries: list[AuditEntry], limit: int) -> AuditPage:
    return AuditPage(
        entries=[AuditEntryOut.model_validate(e, from_attributes=True) for e in entries],
        next_before=entries[-1].seq if len(entries) == limit else None,
    )


def audit_summary(audit: CoverageAudit) -> AuditSummaryOut:
    report = audit.report
    return AuditSummaryOut(
        id=audit.id,
        version=audit.version,
        created_at=audit.created_at,
        who=audit.who,
        batch_sha256=audit.batch_sha256,
        instances=audit.n_instances,
        passed=report["passed"],
        flagged=len(report["flagged"]),
    )


def audit_out(audit: CoverageAudit) -> AuditOut:
    return AuditOut(**audit_summary(audit).model_dump(), report=AuditReportOut.model_validate(audit.report))


def audit_list(model_hash: str, audits: list[CoverageAudit], limit: int) -> AuditList:
    return AuditList(
        model_hash=model_hash,
        audits=[audit_summary(a) for a in audits],
        next_before=audits[-1].id if len(audits) == limit else None,
    )


def drift_out(report: DriftReport) -> DriftOut:
    sequential = report.sequential
    return DriftOut(
        window=report.window,
        statistic=report.test,
        alarm_threshold=report.alarm_threshold,
        alarm=report.alarm,
        independent_looks=None if sequential is None else sequential.looks,
        frames=None if sequential is None else sequential.frames,
        evidence=None if sequential is None else sequential.evidence,
        evidence_threshold=None if sequential is None else sequential.threshold,
        reference_version=report.version,
        reference_available=report.reference_available,
        reason=report.reason,
        recorded=report.recorded,
        evaluated_at=report.evaluated_at,
        process=report.process,
        replicas=report.replicas,
        oldest_share_seconds=round(report.oldest_share_seconds, 3),
        keypoints=[KeypointDriftOut.model_validate(asdict(k)) for k in report.keypoints],
        objects=[ObjectDriftOut.model_validate(asdict(o)) for o in report.objects],
        history=[HistoryPointOut.model_validate(asdict(h)) for h in report.history],
        set_sizes={kind: KindSizesOut.model_validate(asdict(s)) for kind, s in report.set_sizes.items()},
    )
