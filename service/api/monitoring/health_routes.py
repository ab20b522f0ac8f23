"""Liveness, readiness and metrics."""

from __future__ import annotations

from typing import Literal

from fastapi import APIRouter, Response
from pydantic import BaseModel, Field

from service.api.deps import Model, Registry
from service.infra.metrics import metrics_payload

router = APIRouter(tags=["operations"])


class Health(BaseModel):
    status: str


class Readiness(BaseModel):
    status: str
    model: str
    model_hash: str
    active_calibration: int
    store: Literal["ok", "unreachable"] = Field(
        description="whether the calibration store answered the latest poll; predictions go on from"
        " memory while it is unreachable"
    )
    cache_age_seconds: float = Field(
        description="seconds since the store last confirmed the cached active calibration"
    )
    store_error: str | None = Field(description="why the store is unreachable (null while it answers)")


@router.get("/healthz", response_model=Health, summary="The process is alive")
async def healthz() -> Health:
    return Health(status="ok")


@router.get(
    "/readyz",
    response_model=Readiness,
    summary="Model loaded, a calibration active and in memory (the store's health is in the body)",
    responses={503: {"description": "No calibration active or usable"}},
)
async def readyz(registry: Registry, model: Model) -> Readiness:
    active = registry.resolve(None)  # 503: none active, or unusable; never waits on the store
    health = registry.health()
    return Readiness(
        status="ready",
        model=model.manifest.name,
        model_hash=model.model_hash,
        active_calibration=active,
        store="ok" if health.reachable else "unreachable",
        cache_age_seconds=round(health.age_seconds, 3),
        store_error=health.error,
    )


@router.get(
    "/metrics",
    summary="Prometheus metrics",
    response_class=Response,
    responses={200: {"content": {"text/plain": {"schema": {"type": "string"}}}}},
)
async def metrics() -> Response:
    payload, content_type = metrics_payload()
    return Response(payload, media_type=content_type)
