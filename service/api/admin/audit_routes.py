"""Coverage audits: upload a labeled batch to measure a calibration version's coverage on it
(a background job), list the stored audits and read one."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Path, Query
from fastapi.concurrency import run_in_threadpool
from pydantic import Field

from service.api.admin.admin_presenters import audit_list, audit_out
from service.api.admin.admin_schemas import AuditList, AuditOut, JobOut
from service.api.admin.batch_upload import AuditRejectedShare, BatchName, Note, Upload, upload_route
from service.api.deps import ADMIN_RESPONSES, Admin, Audits, Model, Store
from service.api.predict.predict_schemas import MAX_VERSION
from service.errors import NotFound
from service.monitoring.audit_report import DEFAULT_EPSILONS
from service.monitoring.coverage_audits import AuditRequest

router = APIRouter(prefix="/v1/admin", tags=["admin"], responses=ADMIN_RESPONSES)
MAX_AUDIT_ID = 2**63 - 1


@upload_route(
    router,
    ("/audits", "/forms/audits"),  # not /audits/form: that is also GET /audits/{audit_id}'s
    summary="Audit a version's coverage on a labeled batch; a background job (kind audit) stores the report",
    batch=" (the calibration upload format): annotations.json and the images it names, labeled, and never"
    " used to calibrate the audited version",
    responses={
        "404": "version names a version that does not exist",
        "409": "The batch repeats instances the audited version was calibrated with (drop them with"
        " dedupe=true), or the version was scored under other manifest settings",
        "422": "The body is no zip, the archive or its COCO batch is invalid, or an epsilon is outside"
        " (0, 1)",
    },
)
async def start_audit(
    upload: Upload,
    audits: Audits,
    version: Annotated[
        int | None, Query(ge=1, le=MAX_VERSION, description="the version to audit (default: the active one)")
    ] = None,
    epsilon: Annotated[
        list[Annotated[float, Field(gt=0, lt=1)]] | None,
        Query(description="the epsilons to audit at, each in (0, 1), repeated (default 0.05, 0.1 and 0.2)"),
    ] = None,
    name: BatchName = None,
    note: Note = "",
    dedupe: Annotated[
        bool, Query(description="drop instances the version was calibrated with instead of refusing (409)")
    ] = False,
    max_rejected_share: AuditRejectedShare = None,
) -> JobOut:
    async with upload.audited("audit"):
        epsilons = tuple(epsilon or DEFAULT_EPSILONS)
        audit = AuditRequest(version, epsilons, name, note, dedupe, max_rejected_share)
        return await upload.start(audit, audits.accept)


@router.get("/audits", response_model=AuditList, summary="Coverage audits of the served model, newest first")
async def list_audits(
    store: Store,
    model: Model,
    _: Admin,
    before: Annotated[
        int | None, Query(ge=1, le=MAX_AUDIT_ID, description="audits with a smaller id")
    ] = None,
    limit: Annotated[int, Query(ge=1, le=1000)] = 100,
) -> AuditList:
    audits = await run_in_threadpool(store.coverage_audits, model.model_hash, before, limit)
    return audit_list(model.model_hash, audits, limit)


@router.get(
    "/audits/{audit_id}",
    response_model=AuditOut,
    summary="One coverage audit: every figure with its band and p-value, the flags and the advice",
    responses={404: {"description": "No such audit"}},
)
async def get_audit(
    audit_id: Annotated[int, Path(ge=1, le=MAX_AUDIT_ID, description="the audit's id")],
    store: Store,
    model: Model,
    _: Admin,
) -> AuditOut:
    audit = await run_in_threadpool(store.coverage_audit, model.model_hash, audit_id)
    if audit is None:
        raise NotFound(f"no coverage audit {audit_id} of this model: GET /v1/admin/audits lists them")
    return audit_out(audit)
