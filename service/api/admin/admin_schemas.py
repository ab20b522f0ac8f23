"""Bodies of the admin API: calibration versions, jobs, activations, coverage audits."""

from __future__ import annotations

from datetime import datetime
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, StrictBool, model_validator

from service.api.predict.predict_schemas import Nonconformity


class SourceBatchOut(BaseModel):
    name: str
    sha256: str
    instances: int


class VersionSummary(BaseModel):
    version: int
    created_at: datetime
    author: str
    note: str
    parent_version: int | None
    instances: int
    objects: dict[str, int] = Field(description="instances per object")
    source_batches: list[SourceBatchOut]
    active: bool


class ThresholdRow(BaseModel):
    """Thresholds of one function at one epsilon; null means the set is unbounded."""

    nonconformity: Nonconformity
    epsilon: float
    keypoint: dict[str, float | None] = Field(description="keypoint name -> threshold (keypoint scope)")
    object: dict[str, float | None] = Field(description="object name -> threshold (object scope)")


class VersionDetail(VersionSummary):
    normalization: dict = Field(description="the manifest settings the scores were computed under")
    usable: bool = Field(description="whether the current manifest can serve this version")
    unusable_reason: str | None = Field(None, description="why not, and what to do")
    labeled_per_keypoint: dict[str, int] = Field(description="calibration scores per keypoint (n)")
    complete_per_object: dict[str, int] = Field(description="fully labeled instances (object scope n)")
    thresholds: list[ThresholdRow]
    strata: dict | None = Field(
        None,
        description="Mondrian strata stored with the version (null: none): spec (difficulty signals, bins,"
        " min_instances; group), groups (labels known), bins per keypoint channel and group ('*' = all"
        " instances): edges of each signal and the calibration instances (counts) per bin",
    )


class VersionList(BaseModel):
    model_hash: str
    active_version: int | None
    versions: list[VersionSummary]


# JSON Schema's if/then: force (or allow_duplicate, in the upload's query) needs a non-blank reason
_FORCED = {"properties": {"force": {"const": True}}, "required": ["force"]}
NEEDS_REASON = {"required": ["reason"], "properties": {"reason": {"pattern": r"\S"}}}


class ActivationIn(BaseModel):
    """force=true needs a non-blank reason (checked; JSON Schema says so with if/then)."""

    model_config = ConfigDict(extra="forbid", json_schema_extra={"if": _FORCED, "then": NEEDS_REASON})

    reason: str = Field("", max_length=2000, description="why; required (not blank) with force")
    force: StrictBool = Field(
        False, description="activate although the guardrails refuse it (needs a reason; audited)"
    )

    @model_validator(mode="after")
    def _force_needs_a_reason(self) -> ActivationIn:
        if self.force and not self.reason.strip():
            raise ValueError("force=true needs a reason: say why the guardrails may be overridden")
        return self


class KeypointChangeOut(BaseModel):
    keypoint: str
    object: str
    n_before: int | None = Field(description="calibration scores of the active version (null: none active)")
    n_after: int = Field(description="calibration scores of the candidate")
    smallest_bounded_epsilon_before: float | None = Field(description="1/(n+1): below it, sets are unbounded")
    smallest_bounded_epsilon_after: float | None
    set_area_ratio: float | None = Field(
        description="area of the candidate's sets over the active version's, for the same heatmap"
    )
    active_coverage_of_candidate: float | None = Field(
        description="share of the candidate's calibration scores inside the active version's sets"
    )


class ComparisonOut(BaseModel):
    """A candidate version against the active one, and whether the guardrails allow activating it."""

    candidate: int | None
    against: int | None = Field(description="the version compared with (null: nothing is active)")
    nonconformity: Nonconformity
    epsilon: float
    min_instances: int = Field(description="the floor of n per keypoint (CKS_MIN_CALIBRATION_INSTANCES)")
    median_set_area_ratio: float | None
    allowed: bool
    problems: list[str] = Field(description="why activating would be refused (empty: allowed)")
    keypoints: list[KeypointChangeOut]


class AuditEntryOut(BaseModel):
    seq: int
    at: datetime
    who: str = Field(description="the operator (the admin token's name) or the CLI user")
    action: str = Field(description="upload, calibration, activation, rollback, retry")
    outcome: str = Field(description="e.g. accepted, refused, stored, failed, activated, forced")
    version: int | None
    previous_version: int | None
    reason: str
    client: str = Field(description="the client's address")
    details: dict


class AuditPage(BaseModel):
    entries: list[AuditEntryOut] = Field(description="newest first")
    next_before: int | None = Field(description="pass as before= for the next (older) page; null at the end")


class StoreInfo(BaseModel):
    kind: str = Field(description="sqlite or postgresql")
    location: str = Field(description="the database file, or the PostgreSQL URL without password")
    data_dir: str = Field(description="absolute data directory (uploads, kept job uploads, metrics)")
    model_hash: str
    active_version: int | None


class ActivationOut(BaseModel):
    seq: int
    version: int
    activated_at: datetime
    who: str
    reason: str


class ActivationLog(BaseModel):
    active_version: int | None
    activations: list[ActivationOut]


class JobOut(BaseModel):
    id: str
    kind: str
    state: str = Field(description="queued, running, succeeded, failed or interrupted (retryable)")
    version: int | None = Field(None, description="the calibration version the job produced")
    done: int = Field(description="instances scored so far")
    total: int = Field(description="instances to score")
    errors: list[str]
    result: dict
    created_at: datetime
    finished_at: datetime | None


# -- coverage audits (service/monitoring/audit_report.py makes the report) ----------------


class CoverageFigureOut(BaseModel):
    """Empirical coverage against what Theorem 1 predicts for a valid calibration."""

    m: int = Field(description="audited instances (labeled keypoints, or fully labeled objects)")
    covered: int = Field(description="of them, inside their sets")
    coverage: float | None = Field(description="covered / m (null when m = 0)")
    promised: float | None = Field(description="1 - epsilon, the coverage the version promises")
    band: list[float] | None = Field(
        description="the coverage a valid calibration gives this batch with 95% probability: the"
        " Beta-Binomial band for one keypoint (object in object scope); pooled, the calibration's spread"
        " with its units perfectly correlated plus the images' cluster-robust spread (docs/operations.md)"
    )
    in_band: bool
    p_value: float = Field(
        description="one-sided p-value of 'coverage below what the calibration promises' (pooled: normal"
        " approximation with the band's spread)"
    )
    expected: float | None = Field(
        None, description="pooled: the mean coverage the calibration promises its units"
    )
    n: int | None = Field(None, description="calibration instances behind the threshold")
    rank: int | None = Field(None, description="l = floor((n+1) epsilon): Beta(n+1-l, l)")
    adjusted_p_value: float | None = Field(None, description="Holm-adjusted over the audit's tests")
    flagged: bool | None = Field(None, description="significantly low after Holm's correction")


class ObjectCoverageOut(CoverageFigureOut):
    object: str


class KeypointCoverageOut(CoverageFigureOut):
    object: str
    keypoint: str
    index: int = Field(description="the keypoint's output channel")


class CoverageSectionOut(BaseModel):
    nonconformity: Nonconformity
    epsilon: float
    scope: str = Field(description="keypoint or object")
    overall: CoverageFigureOut
    objects: list[ObjectCoverageOut]
    keypoints: list[KeypointCoverageOut] = Field(description="keypoint scope only")


class FlaggedFigureOut(CoverageFigureOut):
    nonconformity: Nonconformity
    epsilon: float
    scope: str
    object: str | None = Field(None, description="null: the section's overall figure")
    keypoint: str | None = None
    index: int | None = None


class AuditBatchOut(BaseModel):
    name: str
    sha256: str
    note: str
    annotations: int = Field(description="annotations in the batch")
    rejected: int = Field(description="instances left out (box rule, strict decoding)")
    rejections: list[str] = Field(description="the first of them, with why")
    duplicates_dropped: int


class AuditReportOut(BaseModel):
    version: int
    band_level: float
    correction: str = Field(description="the multiple-testing correction of the flags: holm")
    family_alpha: float = Field(description="family-wise error rate of the flags")
    tests: int = Field(description="figures tested (exact and pooled)")
    instances: int = Field(description="instances scored")
    passed: bool = Field(description="no figure flagged")
    flagged: list[FlaggedFigureOut] = Field(description="most significant first")
    sections: list[CoverageSectionOut] = Field(description="one per nonconformity, epsilon and scope")
    advice: str = Field(description="what to do: nothing, or how to recalibrate and with how many images")
    batch: AuditBatchOut


class AuditSummaryOut(BaseModel):
    id: int
    version: int = Field(description="the calibration version audited")
    created_at: datetime
    who: str
    batch_sha256: str
    instances: int
    passed: bool
    flagged: int = Field(description="figures flagged")


class AuditOut(AuditSummaryOut):
    report: AuditReportOut


class AuditList(BaseModel):
    model_hash: str
    audits: list[AuditSummaryOut] = Field(description="newest first")
    next_before: int | None = Field(description="pass as before= for the next (older) page; null at the end")


class FeatureTestOut(BaseModel):
    statistic: float | None = Field(description="KS distance D or PSI; null while a side has no values")
    p_value: float | None = Field(description="two-sided KS p-value (exact for small samples); null for psi")
    alarm: bool = Field(description="ks: rejected by Holm at CKS_DRIFT_ALARM_LEVEL; psi: above the threshold")
    live_n: int = Field(description="live values in the window")
    reference_n: int = Field(description="calibration values of the reference version")


class KeypointDriftOut(BaseModel):
    object: str
    keypoint: str
    index: int = Field(description="manifest keypoint channel")
    features: dict[str, FeatureTestOut] = Field(description="peak_probability, gamma, anisotropy")


class ObjectDriftOut(BaseModel):
    object: str
    keypoints: list[int] = Field(description="its keypoint channels")
    features: dict[str, FeatureTestOut] = Field(
        description="largest statistic of its keypoints, their smallest p-value times their number"
        " (Bonferroni), alarm if any keypoint's is raised"
    )
    alarm: bool


class HistoryPointOut(BaseModel):
    time: float = Field(description="unix seconds")
    version: int | None
    recorded: int = Field(description="live values recorded so far")
    alarm: bool
    alarms: int = Field(description="keypoint x feature alarms")
    keypoint_statistics: list[float | None] = Field(
        description="per channel: largest statistic over features"
    )
    object_statistics: dict[str, float | None]


class SizeSummaryOut(BaseModel):
    quantiles: dict[str, float] = Field(description="p05, p25, p50, p75, p95")
    histogram_edges: list[float]
    histogram_counts: list[int]


class KindSizesOut(BaseModel):
    n: int = Field(description="recent sets of this nonconformity function")
    unbounded: int = Field(description="of which unbounded (t = 0)")
    semi_major_px: SizeSummaryOut | None = Field(description="semi-major axis (a ball's radius), image px")
    area_px2: SizeSummaryOut | None = Field(description="area pi a b, image px^2")


class DriftOut(BaseModel):
    window: int = Field(description="live instances kept per keypoint (CKS_DRIFT_WINDOW)")
    statistic: Literal["sequential", "ks", "psi"] = Field(description="the test (CKS_DRIFT_TEST)")
    alarm_threshold: float = Field(
        description="sequential: CKS_DRIFT_ALARM_LEVEL, at least 1/this looks between false alarms; ks:"
        " family-wise error rate of the Holm-corrected alarm; psi: the PSI threshold"
    )
    alarm: bool = Field(
        description="sequential: the evidence reached its threshold; ks, psi: any keypoint's alarm is raised"
    )
    independent_looks: int | None = Field(
        None,
        description="sequential: the independent looks the alarm has tested since the reference version"
        " became active (a scene's frames are one look); null for ks and psi, which count every frame",
    )
    frames: int | None = Field(
        None, description="sequential: frames (requests) recorded by the replicas covered"
    )
    evidence: float | None = Field(
        None,
        description="sequential: the larger of the two e-CUSUMs (1: no evidence); the alarm is raised at"
        " evidence_threshold = 2 / CKS_DRIFT_ALARM_LEVEL",
    )
    evidence_threshold: float | None = Field(None, description="sequential: 2 / CKS_DRIFT_ALARM_LEVEL")
    reference_version: int | None = Field(description="the active calibration version compared with")
    reference_available: bool
    reason: str | None = Field(description="why there is no reference (null when there is)")
    recorded: int = Field(description="live values recorded by the replicas covered")
    evaluated_at: float = Field(description="unix seconds of the evaluation")
    process: int = Field(
        description="the worker process that answered (its windows merged with the other replicas')"
    )
    replicas: int = Field(
        description="worker processes and replicas whose windows and looks this answer covers (this one"
        " included): those that wrote to the store within 5 x CKS_DRIFT_SHARE_SECONDS"
    )
    oldest_share_seconds: float = Field(
        description="age of the oldest other replica's contribution (0: this process alone); each"
        " writes every CKS_DRIFT_SHARE_SECONDS"
    )
    keypoints: list[KeypointDriftOut]
    objects: list[ObjectDriftOut]
    history: list[HistoryPointOut] = Field(description="one point a minute, oldest first")
    set_sizes: dict[str, KindSizesOut] = Field(description="recent sets per nonconformity function")
