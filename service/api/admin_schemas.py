"""Bodies of the admin API: calibration versions, jobs, activations."""

from __future__ import annotations

from datetime import datetime

from pydantic import BaseModel, Field

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


class VersionList(BaseModel):
    model_hash: str
    active_version: int | None
    versions: list[VersionSummary]


class ActivationIn(BaseModel):
    reason: str = Field(default="", max_length=2000)


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
    state: str
    done: int = Field(description="instances scored so far")
    total: int = Field(description="instances to score")
    errors: list[str]
    result: dict
    created_at: datetime
    finished_at: datetime | None
