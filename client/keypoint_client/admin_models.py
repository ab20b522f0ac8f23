"""Bodies of the admin API: calibration versions, comparisons, activations, jobs, the audit trail."""

from __future__ import annotations

from datetime import datetime
from typing import Any, Literal

from pydantic import Field

from keypoint_client.models import Nonconformity
from keypoint_client.sets import Frozen

JobState = Literal["queued", "running", "succeeded", "failed", "interrupted"]
FINISHED: frozenset[str] = frozenset({"succeeded", "failed", "interrupted"})


class SourceBatch(Frozen):
    name: str
    sha256: str
    instances: int


class VersionSummary(Frozen):
    version: int
    created_at: datetime
    author: str
    note: str
    parent_version: int | None
    instances: int
    objects: dict[str, int] = Field(description="instances per object")
    source_batches: list[SourceBatch]
    active: bool


class ThresholdRow(Frozen):
    """Thresholds of one function at one epsilon; None means the set is unbounded."""

    nonconformity: Nonconformity
    epsilon: float
    keypoint: dict[str, float | None]
    object: dict[str, float | None]


class VersionDetail(VersionSummary):
    normalization: dict[str, Any]
    usable: bool = Field(description="whether the current manifest can serve this version")
    unusable_reason: str | None = None
    labeled_per_keypoint: dict[str, int] = Field(description="calibration scores per keypoint (n)")
    complete_per_object: dict[str, int] = Field(description="fully labeled instances (object scope n)")
    thresholds: list[ThresholdRow]
    strata: dict[str, Any] | None = Field(default=None, description="Mondrian strata: spec, groups, bins")


class VersionList(Frozen):
    model_hash: str
    active_version: int | None
    versions: list[VersionSummary]


class KeypointChange(Frozen):
    keypoint: str
    object: str
    n_before: int | None
    n_after: int
    smallest_bounded_epsilon_before: float | None
    smallest_bounded_epsilon_after: float | None
    set_area_ratio: float | None
    active_coverage_of_candidate: float | None


class Comparison(Frozen):
    """A candidate version against another (the active one), and whether the guardrails allow it."""

    candidate: int | None
    against: int | None
    nonconformity: Nonconformity
    epsilon: float
    min_instances: int
    median_set_area_ratio: float | None
    allowed: bool
    problems: list[str] = Field(description="why activating would be refused (empty: allowed)")
    keypoints: list[KeypointChange]


class Activation(Frozen):
    seq: int
    version: int
    activated_at: datetime
    who: str
    reason: str


class ActivationLog(Frozen):
    """Every activation, oldest first; the last one is the active version."""

    active_version: int | None
    activations: list[Activation]

    def previous_version(self) -> int:
        """The version active before the current one: what a rollback goes back to."""
        for entry in reversed(self.activations):
            if entry.version != self.active_version:
                return entry.version
        raise ValueError(
            f"no version other than {self.active_version} was ever active: nothing to roll back to"
        )


class AuditEntry(Frozen):
    seq: int
    at: datetime
    who: str
    action: str
    outcome: str
    version: int | None
    previous_version: int | None
    reason: str
    client: str
    details: dict[str, Any]


class AuditPage(Frozen):
    entries: list[AuditEntry] = Field(description="newest first")
    next_before: int | None = Field(description="pass as before= for the next (older) page; None at the end")


class StoreInfo(Frozen):
    kind: str
    location: str
    data_dir: str
    model_hash: str
    active_version: int | None


class Job(Frozen):
    """A calibration job; ``version`` is the version it produced."""

    id: str
    kind: str
    state: JobState
    version: int | None = None
    done: int = Field(description="instances scored so far")
    total: int = Field(description="instances to score")
    errors: list[str]
    result: dict[str, Any]
    created_at: datetime
    finished_at: datetime | None

    @property
    def finished(self) -> bool:
        return self.state in FINISHED
