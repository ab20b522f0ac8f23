"""GET /v1/admin/drift: the live heatmap features of every keypoint against the calibration's."""

from __future__ import annotations

from dataclasses import asdict
from typing import Literal

from fastapi import APIRouter
from fastapi.concurrency import run_in_threadpool
from pydantic import BaseModel, Field

from service.api.deps import Admin, State
from service.errors import NotFound
from service.monitoring.drift import DriftReport

router = APIRouter(
    prefix="/v1/admin",
    tags=["admin"],
    responses={503: {"description": "The calibration store is unreachable (with Retry-After)"}},
)


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
    statistic: Literal["ks", "psi"] = Field(description="the test (CKS_DRIFT_TEST)")
    alarm_threshold: float = Field(
        description="ks: family-wise error rate of the Holm-corrected alarm; psi: the PSI threshold"
    )
    alarm: bool = Field(description="any keypoint's alarm is raised")
    reference_version: int | None = Field(description="the active calibration version compared with")
    reference_available: bool
    reason: str | None = Field(description="why there is no reference (null when there is)")
    recorded: int = Field(description="live values recorded by this process")
    evaluated_at: float = Field(description="unix seconds of the evaluation")
    process: int = Field(description="the worker process whose windows these are (each keeps its own)")
    keypoints: list[KeypointDriftOut]
    objects: list[ObjectDriftOut]
    history: list[HistoryPointOut] = Field(
        description="one point per CKS_DRIFT_HISTORY_SECONDS, oldest first"
    )
    set_sizes: dict[str, KindSizesOut] = Field(description="recent sets per nonconformity function")


@router.get(
    "/drift",
    response_model=DriftOut,
    summary="Drift of the live heatmap features of every keypoint against the active calibration's",
    responses={404: {"description": "Drift monitoring is off (CKS_DRIFT_ENABLED=false)"}},
)
async def drift(state: State, who: Admin) -> DriftOut:
    if state.drift is None:
        raise NotFound("drift monitoring is off in this server: set CKS_DRIFT_ENABLED=true to turn it on")
    report = await run_in_threadpool(state.drift.report)
    return drift_out(report)


def drift_out(report: DriftReport) -> DriftOut:
    return DriftOut(
        window=report.window,
        statistic=report.test,
        alarm_threshold=report.alarm_threshold,
        alarm=report.alarm,
        reference_version=report.version,
        reference_available=report.reference_available,
        reason=report.reason,
        recorded=report.recorded,
        evaluated_at=report.evaluated_at,
        process=report.process,
        keypoints=[KeypointDriftOut.model_validate(asdict(k)) for k in report.keypoints],
        objects=[ObjectDriftOut.model_validate(asdict(o)) for o in report.objects],
        history=[HistoryPointOut.model_validate(asdict(h)) for h in report.history],
        set_sizes={kind: KindSizesOut.model_validate(asdict(s)) for kind, s in report.set_sizes.items()},
    )

