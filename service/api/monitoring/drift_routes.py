"""GET /v1/admin/drift: the live heatmap features of every keypoint against the calibration's."""

from __future__ import annotations

from fastapi import APIRouter
from fastapi.concurrency import run_in_threadpool

from service.api.admin.admin_presenters import drift_out
from service.api.admin.admin_schemas import DriftOut
from service.api.deps import ADMIN_RESPONSES, Admin, Drift
from service.errors import NotFound

router = APIRouter(prefix="/v1/admin", tags=["admin"], responses=ADMIN_RESPONSES)


@router.get(
    "/drift",
    response_model=DriftOut,
    summary="Drift of the live heatmap features of every keypoint against the active calibration's",
    responses={404: {"description": "Drift monitoring is off (CKS_DRIFT_ENABLED=false)"}},
)
async def drift(monitor: Drift, who: Admin) -> DriftOut:
    if monitor is None:
        raise NotFound("drift monitoring is off in this server: set CKS_DRIFT_ENABLED=true to turn it on")
    return drift_out(await run_in_threadpool(monitor.report))
