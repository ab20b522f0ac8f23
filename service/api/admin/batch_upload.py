"""A labeled batch as the admin API receives it (calibration uploads and coverage audits): the
upload routes' documentation (one operation per request content type), the zip body into an
upload workspace, and every refusal of the action in the audit trail."""

from __future__ import annotations

from collections.abc import AsyncIterator, Callable
from contextlib import asynccontextmanager
from typing import Any

from fastapi import APIRouter, Request
from fastapi.concurrency import run_in_threadpool
from fastapi.types import DecoratedCallable

from calibration_store import StoreFull, StoreUnavailable
from service.api.admin.admin_schemas import JobOut
from service.api.admin.job_links import JOB_LINKS
from service.api.http.request_body import BodyPace, receive_upload
from service.calibration.uploads import UploadWorkspace
from service.errors import ServiceError, disk_full_refused
from service.infra.audit_trail import AuditTrail, Operator
from service.infra.settings import Settings

ZIP_PART = "file"  # the zip's part name when the batch comes as multipart/form-data
# One request content type per operation (client generators keep only one): the raw zip is documented
# as application/octet-stream, the type generators know for bytes, and the form as its own operation
# on its own path. Either path takes either body; a raw body is judged by its bytes whatever its type.
ZIP_RAW: dict[str, Any] = {
    "required": True,
    "content": {"application/octet-stream": {"schema": {"type": "string", "format": "binary"}}},
}
ZIP_FORM: dict[str, Any] = {
    "required": True,
    "content": {
        "multipart/form-data": {
            "schema": {
                "type": "object",
                "required": [ZIP_PART],
                "properties": {ZIP_PART: {"type": "string", "format": "binary", "description": "the zip"}},
            }
        }
    },
}


_RECEIVED = {
    "408": "The body did not arrive within CKS_UPLOAD_READ_TIMEOUT_SECONDS, or slower than"
    " CKS_MIN_BODY_BYTES_PER_SECOND",
    "413": "The zip, its files or its unzipped size exceed the limits",
}


def upload_route(
    router: APIRouter,
    paths: tuple[str, str],
    summary: str,
    batch: str,
    responses: dict[str, str],
    parameters: tuple[dict[str, Any], ...] = (),
) -> Callable[[DecoratedCallable], DecoratedCallable]:
    """The decorator of an upload route, registered twice: the raw zip on ``paths[0]``, the form on
    ``paths[1]`` (operation ``<name>_form``); 202 with the job it starts, the body a zip of a
    COCO-keypoints ``batch``, ``responses`` its refusals besides those of receiving the zip."""
    refusals = {status: {"description": text} for status, text in {**_RECEIVED, **responses}.items()}
    raw = {**ZIP_RAW, "description": f"The raw zip. A zip of a COCO-keypoints batch{batch}"}
    form = {**ZIP_FORM, "description": f"The zip as the part 'file'. A zip of a COCO-keypoints batch{batch}"}
    route = {"status_code": 202, "responses": {202: {"links": JOB_LINKS}}, "response_model": JobOut}

    def register(endpoint: DecoratedCallable) -> DecoratedCallable:
        def post(path: str, body: dict[str, Any], name: str | None, summary: str) -> None:
            extra = {"requestBody": body, "responses": refusals, "parameters": list(parameters)}
            router.post(path, name=name, summary=summary, openapi_extra=extra, **route)(endpoint)

        post(paths[0], raw, None, summary)
        post(paths[1], form, f"{endpoint.__name__}_form", f"{summary} (multipart/form-data)")
        return endpoint

    return register


@asynccontextmanager
async def refusals_audited(
    trail: AuditTrail, operator: Operator, action: str, context: dict | None = None, **fields: Any
) -> AsyncIterator[None]:
    """Append every refusal of an admin action to the audit trail before it is answered, then let
    it through; one the store caused (unreachable, locked, full) is appended once the store can."""
    try:
        yield
    except ServiceError as error:
        details = {
            **(context or {}),
            "status": error.status,
            "detail": error.detail,
            "errors": error.errors[:10],
        }
        await run_in_threadpool(trail.record, operator, action, "refused", details=details, **fields)
        raise
    except StoreUnavailable as error:
        status = 507 if isinstance(error, StoreFull) else 503
        details = {**(context or {}), "status": status, "detail": str(error), "errors": []}
        trail.record_later(operator, action, "refused", details=details, **fields)
        raise


async def receive_batch_zip(request: Request, settings: Settings) -> tuple[UploadWorkspace, str]:
    """Receive a zip body, or a form with the zip as its part 'file', paced and within the upload
    limits, into a new upload workspace; returns it with the zip's sha256 (the caller removes it
    when done). Any type but multipart/form-data is taken as the raw zip: a zip is a zip by its
    bytes (the archive check refuses anything else with 422), whatever Content-Type was sent."""
    content_type = request.headers.get("content-type", "").split(";")[0].strip().lower()
    part = ZIP_PART if content_type == "multipart/form-data" else None
    timeout = settings.calibration.upload_read_timeout_seconds
    pace = BodyPace.from_settings(settings, timeout, "CKS_UPLOAD_READ_TIMEOUT_SECONDS")
    with disk_full_refused("the upload"):
        workspace = await run_in_threadpool(UploadWorkspace.create, settings.storage.uploads_dir)
        try:
            limit = settings.calibration.max_upload_bytes
            saved = await receive_upload(request, workspace.archive, limit, pace, part)
        except BaseException:
            await run_in_threadpool(workspace.remove)
            raise
    return workspace, saved.sha256
