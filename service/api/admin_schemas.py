"""Bodies of the admin API: calibration versions, jobs, activations."""

from __future__ import annotations

from datetime import datetime

from pydantic import BaseModel, Field, model_validator

from service.api.schemas import Nonconformity


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
    unusable_reason: str | None = Field(default=None, description="why not, and what to do")
    labeled_per_keypoint: dict[str, int] = Field(description="calibration scores per keypoint (n)")
    complete_per_object: dict[str, int] = Field(description="fully labeled instances (object scope n)")
    thresholds: list[ThresholdRow]
    strata: dict | None = Field(
        default=None,
        description="Mondrian strata stored with the version (null: none): spec (difficulty signals, bins,"
        " min_instances; group), groups (labels known), bins per keypoint channel and group ('*' = all"
        " instances): edges of each signal and the calibration instances (counts) per bin",
    )


class VersionList(BaseModel):
    model_hash: str
    active_version: int | None
    versions: list[VersionSummary]


class ActivationIn(BaseModel):
    reason: str = Field(default="", max_length=2000, description="why; required with force")
    force: bool = Field(
        default=False, description="activate although the guardrails refuse it (needs a reason; audited)"
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
    version: int | None = Field(default=None, description="the calibration version the job produced")
    done: int = Field(description="instances scored so far")
    total: int = Field(description="instances to score")
    errors: list[str]
    result: dict
    created_at: datetime
    finished_at: datetime | None
