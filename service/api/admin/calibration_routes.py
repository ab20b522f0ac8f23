"""Calibration administration: uploads, jobs, versions (list, compare, activate), audit trail, store."""

from __future__ import annotations

from typing import Annotated, Any, Literal

from fastapi import APIRouter, Body, Path, Query, Response
from fastapi.concurrency import run_in_threadpool
from pydantic import Field

from calibration_store import VersionNotFound, store_location
from service.api.admin import admin_presenters as present
from service.api.admin import admin_schemas as out
from service.api.admin.batch_upload import (
    BatchName,
    BatchRejectedShare,
    Note,
    Upload,
    refusals_audited,
    upload_route,
)
from service.api.admin.job_links import JOB_RESULT_LINKS
from service.api.deps import ADMIN_RESPONSES, Admin, Calibrations, Config, Jobs, Model, Registry, Store, Trail
from service.api.predict.predict_schemas import MAX_VERSION, Nonconformity, Stratify
from service.calibration.intake import UploadOptions
from service.calibration.stratification import parse_stratify
from service.calibration.versions import ActivationRequest, activate, comparison_with
from service.errors import NotFound

router = APIRouter(prefix="/v1/admin", tags=["admin"], responses=ADMIN_RESPONSES)
DISK_FULL = "No room on disk for what the call writes (a full disk or store): nothing was kept; retry later"
VersionNumber = Annotated[int, Path(ge=1, le=MAX_VERSION, description="calibration version number")]


def _flag(description: str) -> dict[str, Any]:
    return {"type": "boolean", "default": False, "description": description}


# force, allow_duplicate and reason as one exploded query object (sent as force=true&reason=...,
# as always), so that JSON Schema can say the rule: either flag needs a non-blank reason.
_OVERRIDES = {
    "name": "overrides",
    "in": "query",
    "style": "form",
    "explode": True,
    "description": "sent as the query parameters force, allow_duplicate and reason (reason required,"
    " not blank, with either flag)",
    "schema": {
        "type": "object",
        "properties": {
            "force": _flag("with activate=true only: activate even if the guardrails refuse (needs reason)"),
            "allow_duplicate": _flag(
                "store a version equal to a stored one instead of refusing (409) (needs reason)"
            ),
            "reason": {
                "type": "string",
                "maxLength": 2000,
                "default": "",
                "description": "why (recorded; required with force or allow_duplicate)",
            },
        },
        "if": {
            "anyOf": [
                {"properties": {flag: {"const": True}}, "required": [flag]}
                for flag in ("force", "allow_duplicate")
            ]
        },
        "then": out.NEEDS_REASON,
    },
}
_NO_SUCH_VERSION: dict[int | str, dict[str, Any]] = {404: {"description": "No such version"}}
_ACTIVATE_RESPONSES: dict[int | str, dict[str, Any]] = {
    **_NO_SUCH_VERSION,
    409: {
        "description": "Refused by the guardrails (a keypoint's n below CKS_MIN_CALIBRATION_INSTANCES or"
        " below half the active version's; the body's `comparison` says where), or the version was"
        " scored under other manifest settings"
    },
    422: {"description": "force without a reason"},
    507: {"description": DISK_FULL},
}


@upload_route(
    router,
    ("/calibrations", "/forms/calibrations"),  # not /calibrations/form: GET /calibrations/{version}'s too
    summary="Upload a labeled batch; a background job scores it into a new version",
    batch=": annotations.json and the images it names",
    responses={
        "404": "append_to names a version that does not exist",
        "409": "The batch repeats images or instances already counted (inside itself or in append_to):"
        " the problem lists them; or append_to was scored under other manifest settings; or the batch"
        " would make a version equal to a stored one (`duplicate_of` names it)",
        "422": "The body is no zip, the archive or its COCO batch is invalid, more instances break the"
        " box rule than max_rejected_share allows, or force or allow_duplicate without a reason; the"
        " problem lists what to fix",
        "503": "The calibration store could not record the job",
        "507": DISK_FULL,
    },
    parameters=(_OVERRIDES,),
)
async def upload_calibration(
    upload: Upload,
    calibrations: Calibrations,
    name: BatchName = None,
    append_to: Annotated[
        int | None, Query(ge=1, le=MAX_VERSION, description="new version = this version + the batch")
    ] = None,
    activate: Annotated[bool, Query(description="activate the new version when the job succeeds")] = False,
    force: Annotated[bool, Query(include_in_schema=False)] = False,  # documented in _OVERRIDES
    reason: Annotated[str, Query(max_length=2000, include_in_schema=False)] = "",
    dedupe: Annotated[
        bool, Query(description="drop instances already counted instead of refusing the batch (409)")
    ] = False,
    allow_duplicate: Annotated[bool, Query(include_in_schema=False)] = False,
    max_rejected_share: BatchRejectedShare = None,
    note: Note = "",
    stratify: Annotated[
        list[Stratify] | None,
        Query(
            description="Mondrian strata to store: none, difficulty, group, difficulty+group (or the"
            " parameter repeated); default: difficulty when the scores carry heatmap features"
        ),
    ] = None,
) -> out.JobOut:
    async with upload.audited("upload"):
        options = UploadOptions(
            name=name,
            note=note,
            append_to=append_to,
            activate=activate,
            force=force,
            reason=reason,
            dedupe=dedupe,
            allow_duplicate=allow_duplicate,
            max_rejected_share=max_rejected_share,
            # repeated values are quoted as one ("difficulty+bogus") when refused, as they always were
            stratify=None if stratify is None else parse_stratify("+".join(stratify)),
        )
        return await upload.start(options, calibrations.accept)


@router.get(
    "/jobs/{job_id}",
    response_model=out.JobOut,
    summary="State, progress and errors of a job (any replica answers)",
    responses={
        200: {"links": JOB_RESULT_LINKS},
        404: {"description": "No such job (never existed, or pruned)"},
        503: {"description": "The calibration store is unreachable"},
    },
)
async def get_job(job_id: str, jobs: Jobs, registry: Registry, _: Admin) -> out.JobOut:
    job = await run_in_threadpool(jobs.get, job_id)
    if job is None:
        raise NotFound(
            f"no job {job_id!r}: it never existed or was pruned (a job is kept for 7 days after its"
            " last heartbeat, and of the finished jobs only the latest 1000)"
        )
    if job.state == "succeeded" and job.result.get("activated"):  # the server that says so serves it
        await run_in_threadpool(registry.refresh_now)
    return present.job_out(job)


@router.post(
    "/jobs/{job_id}/retry",
    status_code=202,
    response_model=out.JobOut,
    summary="Run an interrupted job again from its kept upload (a new job)",
    responses={
        404: {"description": "No such job"},
        409: {"description": "The job is not interrupted, or its upload is kept by another server"},
        507: {"description": DISK_FULL},
    },
)
async def retry_job(
    job_id: str, response: Response, calibrations: Calibrations, trail: Trail, who: Admin
) -> out.JobOut:
    async with refusals_audited(trail, who, "retry", {"job": job_id}):
        job = await run_in_threadpool(calibrations.retry, job_id, who)
    response.headers["Location"] = f"/v1/admin/jobs/{job.id}"
    return present.job_out(job)


@router.get(
    "/calibrations", response_model=out.VersionList, summary="All calibration versions of the served model"
)
async def list_calibrations(store: Store, model: Model, registry: Registry, _: Admin) -> out.VersionList:
    versions = await run_in_threadpool(store.list_versions, model.model_hash)
    active = await run_in_threadpool(registry.refresh_now)
    summaries = [present.summarize(info, active) for info in versions]
    return out.VersionList(model_hash=model.model_hash, active_version=active, versions=summaries)


@router.get(
    "/calibrations/{version}",
    response_model=out.VersionDetail,
    summary="One version in detail",
    responses=_NO_SUCH_VERSION,
)
async def get_calibration(
    version: VersionNumber, store: Store, model: Model, registry: Registry, _: Admin
) -> out.VersionDetail:
    def build() -> out.VersionDetail:
        try:
            info = store.get_version(model.model_hash, version)
        except VersionNotFound as error:
            raise NotFound(f"calibration version {version} does not exist for this model") from error
        return present.describe(info, registry.refresh_now(), registry, model.manifest)

    return await run_in_threadpool(build)


@router.get(
    "/calibrations/{version}/compare",
    response_model=out.ComparisonOut,
    summary="Dry run: compare a version with the active one (or another) without activating",
    responses=_NO_SUCH_VERSION,
)
async def compare_calibration(
    version: VersionNumber,
    model: Model,
    registry: Registry,
    settings: Config,
    _: Admin,
    against: Annotated[
        Literal["active"] | Annotated[int, Field(ge=1, le=MAX_VERSION)],
        Query(description="'active' or a version number"),
    ] = "active",
    epsilon: Annotated[float, Query(gt=0, lt=1, description="the epsilon the sets are compared at")] = 0.1,
    nonconformity: Annotated[Nonconformity, Query()] = "cov",
) -> out.ComparisonOut:
    def build() -> out.ComparisonOut:
        reference = registry.refresh_now() if against == "active" else against
        minimum = settings.calibration.min_instances
        return present.comparison_out(
            comparison_with(registry, model.manifest, version, reference, minimum, epsilon, nonconformity)
        )

    return await run_in_threadpool(build)


@router.post(
    "/calibrations/{version}/activate",
    response_model=out.ActivationOut,
    summary="Make a version active (activating an older one is a rollback), behind the guardrails",
    responses=_ACTIVATE_RESPONSES,
)
async def activate_calibration(
    version: VersionNumber,
    model: Model,
    registry: Registry,
    trail: Trail,
    settings: Config,
    who: Admin,
    # optional, documented as one schema (not anyOf with null): generators keep the body typed
    body: Annotated[out.ActivationIn, Body(default_factory=out.ActivationIn)],
) -> out.ActivationOut:
    request = ActivationRequest(version, who, body.reason, body.force)
    async with refusals_audited(trail, who, "activation", version=version, reason=body.reason):
        entry, _ = await run_in_threadpool(
            activate, registry, model.manifest, trail, request, settings.calibration.min_instances
        )
    return present.activation_out(entry)


@router.get("/activations", response_model=out.ActivationLog, summary="The append-only activation history")
async def activation_log(store: Store, model: Model, registry: Registry, _: Admin) -> out.ActivationLog:
    entries = await run_in_threadpool(store.activation_log, model.model_hash)
    active = await run_in_threadpool(registry.refresh_now)
    return out.ActivationLog(active_version=active, activations=[present.activation_out(e) for e in entries])


@router.get("/audit", response_model=out.AuditPage, summary="The append-only audit trail, newest first")
async def audit_trail(
    store: Store,
    model: Model,
    _: Admin,
    before: Annotated[int | None, Query(ge=1, le=2**63 - 1, description="entries before this seq")] = None,
    limit: Annotated[int, Query(ge=1, le=1000)] = 100,
) -> out.AuditPage:
    entries = await run_in_threadpool(store.audit_log, model.model_hash, before, limit)
    return present.audit_page(entries, limit)


@router.get("/store", response_model=out.StoreInfo, summary="Which calibration store this server uses")
async def store_info(model: Model, registry: Registry, settings: Config, _: Admin) -> out.StoreInfo:
    kind, location = store_location(settings.storage.resolved_url)
    active = await run_in_threadpool(registry.refresh_now)
    data_dir = str(settings.storage.data_dir)
    return out.StoreInfo(
        kind=kind, location=location, data_dir=data_dir, model_hash=model.model_hash, active_version=active
    )
