"""Calibration administration: upload batches, watch jobs, list, inspect, activate, roll back."""

from __future__ import annotations

from typing import Annotated

from fastapi import APIRouter, Path, Query, Request, Response
from fastapi.concurrency import run_in_threadpool

from calibration_store import VersionNotFound
from service.api.admin_schemas import (
    ActivationIn,
    ActivationLog,
    ActivationOut,
    JobOut,
    VersionDetail,
    VersionList,
)
from service.api.body import receive_upload
from service.api.deps import Admin, State
from service.api.presenters import activation_out, describe, job_out, summarize
from service.api.schemas import MAX_VERSION
from service.calibration.archive import ArchiveLimits
from service.calibration.calibrate import CalibrationOptions, check_parent, create_calibration
from service.calibration.jobs import JobProgress
from service.calibration.uploads import UploadWorkspace, batch_name, validate_upload
from service.errors import NotFound, UnsupportedMediaType

router = APIRouter(prefix="/v1/admin", tags=["admin"])
VersionNumber = Annotated[int, Path(ge=1, le=MAX_VERSION, description="calibration version number")]

_ZIP_TYPES = {"application/zip", "application/x-zip-compressed", "application/octet-stream"}
_UPLOAD_OPENAPI = {
    "requestBody": {
        "required": True,
        "description": "A zip of a COCO-keypoints batch: annotations.json and the images it names",
        "content": {"application/zip": {"schema": {"type": "string", "format": "binary"}}},
    },
    "responses": {
        "409": {"description": "append_to names a version scored under other manifest settings"},
        "413": {"description": "The zip, its files or its unzipped size exceed the limits"},
        "415": {"description": "Not a zip body"},
        "422": {"description": "The archive or its COCO batch is invalid; the problem lists what to fix"},
        "503": {"description": "The calibration store could not record the job"},
    },
}


@router.post(
    "/calibrations",
    status_code=202,
    response_model=JobOut,
    summary="Upload a labeled batch; a background job scores it into a new version",
    openapi_extra=_UPLOAD_OPENAPI,
)
async def upload_calibration(
    request: Request,
    response: Response,
    state: State,
    who: Admin,
    name: Annotated[
        str | None, Query(max_length=200, description="batch name (default: upload-<sha256>)")
    ] = None,
    append_to: Annotated[
        int | None, Query(ge=1, le=MAX_VERSION, description="new version = this version + the batch")
    ] = None,
    activate: Annotated[bool, Query(description="activate the new version when the job succeeds")] = False,
    note: Annotated[str, Query(max_length=2000)] = "",
) -> JobOut:
    content_type = request.headers.get("content-type", "").split(";")[0].strip().lower()
    if content_type not in _ZIP_TYPES:
        raise UnsupportedMediaType(
            f"send the batch as a zip body (Content-Type: application/zip), not {content_type!r}"
        )
    workspace = await run_in_threadpool(UploadWorkspace.create, state.uploads_dir)
    try:
        saved = await receive_upload(request, workspace.archive, state.settings.max_upload_bytes)
        named = await run_in_threadpool(
            validate_upload,
            workspace,
            batch_name(name, saved.sha256),
            saved.sha256,
            state.detector.manifest,
            ArchiveLimits.from_settings(state.settings),
        )
        if append_to is not None:
            await run_in_threadpool(check_parent, state.store, state.detector, append_to)
    except BaseException:
        await run_in_threadpool(workspace.remove)
        raise
    options = CalibrationOptions(author=who, note=note, append_to=append_to, activate=activate)

    def run(progress: JobProgress) -> dict:
        try:
            info = create_calibration(
                state.store,
                state.detector,
                [named],
                options,
                state.settings.max_image_pixels,
                progress.advance,
            )
        finally:
            workspace.remove()
        state.registry.refresh_now()
        return {"version": info.number, "instances": info.n_instances, "activated": activate}

    try:
        job = await run_in_threadpool(state.jobs.submit, "calibration", run, named.batch.count)
    except BaseException:
        await run_in_threadpool(workspace.remove)
        raise
    response.headers["Location"] = f"/v1/admin/jobs/{job.id}"
    return job_out(job)


@router.get(
    "/jobs/{job_id}",
    response_model=JobOut,
    summary="State, progress and errors of a job (any replica answers)",
    responses={
        404: {"description": "No such job (never existed, or pruned)"},
        503: {"description": "The calibration store is unreachable"},
    },
)
async def get_job(job_id: str, state: State, _: Admin) -> JobOut:
    job = await run_in_threadpool(state.jobs.get, job_id)
    if job is None:
        raise NotFound(
            f"no job {job_id!r}: it never existed or was pruned (a job is kept for 7 days after its"
            " last heartbeat, and of the finished jobs only the latest 1000)"
        )
    return job_out(job)


@router.get(
    "/calibrations", response_model=VersionList, summary="All calibration versions of the served model"
)
async def list_calibrations(state: State, _: Admin) -> VersionList:
    versions = await run_in_threadpool(state.store.list_versions, state.detector.model_hash)
    active = await run_in_threadpool(state.registry.refresh_now)
    return VersionList(
        model_hash=state.detector.model_hash,
        active_version=active,
        versions=[summarize(info, active) for info in versions],
    )


@router.get("/calibrations/{version}", response_model=VersionDetail, summary="One version in detail")
async def get_calibration(version: VersionNumber, state: State, _: Admin) -> VersionDetail:
    def build() -> VersionDetail:
        try:
            info = state.store.get_version(state.detector.model_hash, version)
        except VersionNotFound as error:
            raise NotFound(f"calibration version {version} does not exist for this model") from error
        return describe(info, state.registry.refresh_now(), state.registry, state.detector.manifest)

    return await run_in_threadpool(build)


@router.post(
    "/calibrations/{version}/activate",
    response_model=ActivationOut,
    summary="Make a version active (activating an older one is a rollback)",
    responses={409: {"description": "The version was scored under other manifest settings"}},
)
async def activate_calibration(
    version: VersionNumber, state: State, who: Admin, body: ActivationIn | None = None
) -> ActivationOut:
    reason = body.reason if body else ""

    def run() -> ActivationOut:
        state.registry.check_usable(version)
        try:
            entry = state.store.activate(state.detector.model_hash, version, who, reason)
        except VersionNotFound as error:
            raise NotFound(f"calibration version {version} does not exist for this model") from error
        state.registry.refresh_now()
        return activation_out(entry)

    return await run_in_threadpool(run)


@router.get("/activations", response_model=ActivationLog, summary="The append-only activation history")
async def activation_log(state: State, _: Admin) -> ActivationLog:
    entries = await run_in_threadpool(state.store.activation_log, state.detector.model_hash)
    active = await run_in_threadpool(state.registry.refresh_now)
    return ActivationLog(active_version=active, activations=[activation_out(e) for e in entries])
