"""Turn stored calibration versions into the admin API's response bodies."""

from __future__ import annotations

import math
from dataclasses import asdict

from calibration_store import Activation, AuditEntry, CoverageAudit, JobRecord, VersionInfo
from service.api.admin import admin_schemas as out
from service.calibration.guardrails import Comparison
from service.calibration.registry import CalibrationRegistry
from service.conformal import NONCONFORMITY_SCORES
from service.detector.manifest import Manifest
from service.monitoring.drift_monitor import DriftReport

REPORTED_EPSILONS = (0.05, 0.1, 0.2)


def summarize(info: VersionInfo, active: int | None) -> out.VersionSummary:
    same = {name: getattr(info, name) for name in ("created_at", "author", "note", "parent_version")}
    renamed = {"version": info.number, "instances": info.n_instances, "objects": dict(info.object_counts)}
    batches = [b.as_dict() for b in info.source_batches]
    return out.VersionSummary(**same, **renamed, source_batches=batches, active=info.number == active)


def describe(
    info: VersionInfo, active: int | None, registry: CalibrationRegistry, manifest: Manifest
) -> out.VersionDetail:
    def finite(values, channels) -> dict[str, float | None]:
        return {name: float(values[c]) if math.isfinite(values[c]) else None for name, c in channels}

    keypoints = [(k.name, k.index) for k in manifest.keypoints]
    objects = [(o.name, o.keypoints[0]) for o in manifest.objects]
    rows = []
    for kind in NONCONFORMITY_SCORES:
        for epsilon in REPORTED_EPSILONS:
            per_keypoint = registry.thresholds(info.number, kind, "keypoint", epsilon, None)
            per_object = registry.thresholds(info.number, kind, "object", epsilon, None)
            keypoint, object_ = finite(per_keypoint.values, keypoints), finite(per_object.values, objects)
            rows.append({"nonconformity": kind, "epsilon": epsilon, "keypoint": keypoint, "object": object_})
    unusable_reason = registry.incompatibility(info.number)
    return out.VersionDetail(
        **summarize(info, active).model_dump(),
        normalization=dict(info.normalization),
        usable=unusable_reason is None,
        unusable_reason=unusable_reason,
        labeled_per_keypoint={name: per_keypoint.guarantees[c].n for name, c in keypoints},
        complete_per_object={name: per_object.guarantees[c].n for name, c in objects},
        thresholds=rows,
        strata=None if info.strata is None else dict(info.strata),
    )


def activation_out(entry: Activation) -> out.ActivationOut:
    return out.ActivationOut.model_validate(entry, from_attributes=True)


def job_out(job: JobRecord) -> out.JobOut:
    return out.JobOut.model_validate(job, from_attributes=True)


def comparison_out(comparison: Comparison) -> out.ComparisonOut:
    return out.ComparisonOut.model_validate(comparison.as_dict())


def audit_page(entries: list[AuditEntry], limit: int) -> out.AuditPage:
    return out.AuditPage(
        entries=[out.AuditEntryOut.model_validate(e, from_attributes=True) for e in entries],
        next_before=entries[-1].seq if len(entries) == limit else None,
    )


def audit_summary(audit: CoverageAudit) -> out.AuditSummaryOut:
    same = {name: getattr(audit, name) for name in ("id", "version", "created_at", "who", "batch_sha256")}
    counts = {"instances": audit.n_instances, "flagged": len(audit.report["flagged"])}
    return out.AuditSummaryOut(**same, **counts, passed=audit.report["passed"])


def audit_out(audit: CoverageAudit) -> out.AuditOut:
    return out.AuditOut(**audit_summary(audit).model_dump(), report=audit.report)


def audit_list(model_hash: str, audits: list[CoverageAudit], limit: int) -> out.AuditList:
    summaries = [audit_summary(a) for a in audits]
    return out.AuditList(
        model_hash=model_hash, audits=summaries, next_before=audits[-1].id if len(audits) == limit else None
    )


def drift_out(report: DriftReport) -> out.DriftOut:
    body = asdict(report) | {"statistic": report.test, "reference_version": report.version}
    body["oldest_share_seconds"] = round(report.oldest_share_seconds, 3)
    if (sequential := report.sequential) is not None:
        body |= {"independent_looks": sequential.looks, "frames": sequential.frames}
        body |= {"evidence": sequential.evidence, "evidence_threshold": sequential.threshold}
    return out.DriftOut.model_validate(body)
