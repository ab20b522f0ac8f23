"""Liveness, readiness and metrics."""

from __future__ import annotations

from fastapi import APIRouter, Response
from fastapi.concurrency import run_in_threadpool
from pydantic import BaseModel

from service.api.deps import State
from service.errors import Unavailable
from service.metrics import metrics_payload

router = APIRouter(tags=["operations"])


class Health(BaseModel):
    status: str


class Readiness(BaseModel):
    status: str
    model: str
    model_hash: str
    active_calibration: int


@router.get("/healthz", response_model=Health, summary="The process is alive")
async def healthz() -> Health:
    return Health(status="ok")


@router.get("/readyz", response_model=Readiness, summary="Model loaded, store reachable, calibration active")
async def readyz(state: State) -> Readiness:
    try:
        await run_in_threadpool(state.store.ping)
    except Exception as error:
        raise Unavailable(f"the calibration store is unreachable: {error}") from error
    active = await run_in_threadpool(state.registry.resolve, None)  # 503: none active, or unusable
    manifest = state.detector.manifest
    return Readiness(
        status="ready", model=manifest.name, model_hash=state.detector.model_hash, active_calibration=active
    )


@router.get("/metrics", summary="Prometheus metrics", response_class=Response)
async def metrics() -> Response:
    payload, content_type = metrics_payload()
    return Response(payload, media_type=content_type)
