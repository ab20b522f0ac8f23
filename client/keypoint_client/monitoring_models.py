"""Bodies of the monitoring API: coverage audits of a calibration version on a labeled batch,
and the drift of the live heatmap features against the active calibration's."""

from __future__ import annotations

from datetime import datetime
from typing import Any, Literal

from pydantic import Field

from keypoint_client.models import Coverage, Nonconformity
from keypoint_client.sets import Frozen

# -- coverage audits


class CoverageFigure(Frozen):
    """Empirical coverage against what Theorem 1 (Yang & Pavone) predicts for a valid calibration."""

    m: int = Field(description="audited instances (labeled keypoints, or fully labeled objects)")
    covered: int = Field(description="of them, inside their sets")
    coverage: float | None = Field(description="covered / m (None when m = 0)")
    promised: float | None = Field(description="1 - epsilon, the coverage the version promises")
    band: list[float] | None = Field(description="the coverage a valid calibration gives, 95% of the time")
    in_band: bool
    p_value: float = Field(description="one-sided p-value of 'coverage below 1 - epsilon'")
    n: int | None = Field(default=None, description="calibration instances behind the threshold")
    rank: int | None = Field(default=None, description="l = floor((n+1) epsilon): Beta(n+1-l, l)")
    adjusted_p_value: float | None = Field(default=None, description="Holm-adjusted over the audit's tests")
    flagged: bool | None = Field(default=None, description="significantly low after Holm's correction")
    expected: float | None = Field(default=None, description="pooled: the mean coverage promised its units")


class ObjectCoverage(CoverageFigure):
    object: str


class KeypointCoverage(CoverageFigure):
    object: str
    keypoint: str
    index: int = Field(description="the keypoint's output channel")


class CoverageSection(Frozen):
    """The figures of one nonconformity function, epsilon and scope."""

    nonconformity: Nonconformity
    epsilon: float
    scope: Coverage
    overall: CoverageFigure
    objects: list[ObjectCoverage]
    keypoints: list[KeypointCoverage] = Field(description="keypoint scope only")


class FlaggedFigure(CoverageFigure):
    nonconformity: Nonconformity
    epsilon: float
    scope: Coverage
    object: str | None = Field(default=None, description="None: the section's overall figure")
    keypoint: str | None = None
    index: int | None = None


class AuditBatch(Frozen):
    name: str
    sha256: str
    note: str
    annotations: int = Field(description="annotations in the batch")
    rejected: int = Field(description="instances left out (box rule, strict decoding)")
    rejections: list[str] = Field(description="the first of them, with why")
    duplicates_dropped: int


class AuditReport(Frozen):
    version: int
    band_level: float
    correction: str = Field(description="the multiple-testing correction of the flags: holm")
    family_alpha: float = Field(description="family-wise error rate of the flags")
    tests: int = Field(description="exact figures tested")
    instances: int = Field(description="instances scored")
    passed: bool = Field(description="no figure flagged")
    flagged: list[FlaggedFigure] = Field(description="most significant first")
    sections: list[CoverageSection] = Field(description="one per nonconformity, epsilon and scope")
    advice: str = Field(description="what to do: nothing, or how to recalibrate and with how many images")
    batch: AuditBatch


class CoverageAuditSummary(Frozen):
    id: int
    version: int = Field(description="the calibration version audited")
    created_at: datetime
    who: str
    batch_sha256: str
    instances: int
    passed: bool
    flagged: int = Field(description="figures flagged")


class CoverageAudit(CoverageAuditSummary):
    """A stored coverage audit: its summary and the full report."""

    report: AuditReport


class CoverageAuditList(Frozen):
    model_hash: str
    audits: list[CoverageAuditSummary] = Field(description="newest first")
    next_before: int | None = Field(description="pass as before= for the next (older) page; None at the end")


# -- drift


class FeatureTest(Frozen):
    statistic: float | None = Field(description="KS distance D or PSI; None while a side has no values")
    p_value: float | None = Field(description="two-sided KS p-value; None for psi")
    alarm: bool
    live_n: int = Field(description="live values in the window")
    reference_n: int = Field(description="calibration values of the reference version")


class KeypointDrift(Frozen):
    object: str
    keypoint: str
    index: int = Field(description="manifest keypoint channel")
    features: dict[str, FeatureTest] = Field(description="peak_probability, gamma, anisotropy")


class ObjectDrift(Frozen):
    object: str
    keypoints: list[int] = Field(description="its keypoint channels")
    features: dict[str, FeatureTest]
    alarm: bool


class DriftHistoryPoint(Frozen):
    time: float = Field(description="unix seconds")
    version: int | None
    recorded: int = Field(description="live values recorded so far")
    alarm: bool
    alarms: int = Field(description="keypoint x feature alarms")
    keypoint_statistics: list[float | None] = Field(description="per channel: the largest over features")
    object_statistics: dict[str, float | None]


class SizeSummary(Frozen):
    quantiles: dict[str, float] = Field(description="p05, p25, p50, p75, p95")
    histogram_edges: list[float]
    histogram_counts: list[int]


class SetSizes(Frozen):
    n: int = Field(description="recent sets of this nonconformity function")
    unbounded: int = Field(description="of which unbounded (t = 0)")
    semi_major_px: SizeSummary | None = Field(description="semi-major axis (a ball's radius), image px")
    area_px2: SizeSummary | None = Field(description="area pi a b, image px^2")


class Drift(Frozen):
    """The live heatmap features of every keypoint against the active calibration's, for every
    worker process and replica that shares its windows (``replicas``), whichever answers."""

    window: int = Field(description="live instances kept per keypoint (CKS_DRIFT_WINDOW)")
    statistic: Literal["sequential", "ks", "psi"] = Field(description="the test (CKS_DRIFT_TEST)")
    alarm_threshold: float
    alarm: bool = Field(description="any keypoint's alarm is raised")
    reference_version: int | None = Field(description="the active calibration version compared with")
    reference_available: bool
    reason: str | None = Field(description="why there is no reference (None when there is)")
    recorded: int = Field(description="live values recorded by the replicas covered")
    evaluated_at: float = Field(description="unix seconds of the evaluation")
    process: int = Field(description="the worker process that answered")
    replicas: int = Field(description="worker processes and replicas covered")
    oldest_share_seconds: float = Field(
        description="age of the oldest other replica's contribution (0: one process)"
    )
    independent_looks: int | None = Field(
        default=None, description="sequential: independent looks tested (a scene's frames are one)"
    )
    frames: int | None = Field(default=None, description="sequential: frames (requests) recorded")
    evidence: float | None = Field(default=None, description="sequential: the larger e-CUSUM (1: none)")
    evidence_threshold: float | None = Field(
        default=None, description="sequential: 2 / CKS_DRIFT_ALARM_LEVEL"
    )
    keypoints: list[KeypointDrift]
    objects: list[ObjectDrift]
    history: list[DriftHistoryPoint] = Field(description="oldest first")
    set_sizes: dict[str, SetSizes] = Field(description="recent sets per nonconformity function")


# -- feedback and live coverage


class JudgedKeypoint(Frozen):
    instance: int
    index: int
    name: str
    covered: bool = Field(description="the true point lay in the set served")
    scores: dict[str, float]


class FeedbackResult(Frozen):
    prediction_id: str
    calibration_version: int
    labelled: int
    covered: int
    keypoints: list[JudgedKeypoint]


class GroupCoverage(Frozen):
    """The field labels' coverage of one group so far (see GET /v1/admin/coverage/live)."""

    level: str  # version, object, keypoint, stream, group (the caller's) or stratum (Mondrian)
    name: str
    version: int
    guarantee: str  # exchangeable, or adaptive (ACI: no floor, no alarm)
    nonconformity: Nonconformity
    coverage: Coverage
    epsilon: float
    delta: float | None
    labelled: int
    covered: int
    looks: int
    look_mean: float | None
    lower: float
    upper: float
    promised: float
    floor: float
    alarm: bool


class LiveCoverage(Frozen):
    alarm_level: float
    alarm: bool
    groups: list[GroupCoverage]


class FieldCalibration(Frozen):
    """A version made from labelled feedback; ``summary`` as a calibration job's result."""

    version: int
    activated: bool
    summary: dict[str, Any]
