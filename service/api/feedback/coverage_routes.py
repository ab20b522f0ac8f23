"""GET /v1/admin/coverage/live: the field labels' coverage of each version's sets, with its alarm."""

from __future__ import annotations

import asyncio
from dataclasses import asdict

from fastapi import APIRouter

from service.api.deps import ADMIN_RESPONSES, Admin, LiveCoverage
from service.api.feedback.feedback_schemas import LiveCoverageOut

router = APIRouter(prefix="/v1/admin", tags=["admin"], responses=ADMIN_RESPONSES)


@router.get(
    "/coverage/live",
    response_model=LiveCoverageOut,
    summary="Coverage of the sets served, from feedback labels: per version, object, keypoint, stream,"
    " group; an anytime-valid confidence sequence and an alarm when coverage is proven below the promise",
)
async def live_coverage(reader: LiveCoverage, who: Admin) -> LiveCoverageOut:
    groups = await asyncio.to_thread(reader.report)
    return LiveCoverageOut(
        alarm_level=reader.level,
        alarm=any(g.alarm for g in groups),
        groups=[asdict(g) for g in groups],
    )
