"""A labeled batch as the admin API receives it (calibration uploads and coverage audits): the
zip body into an upload workspace, and every refusal of the action in the audit trail."""

from __future__ import annotations

from collections.abc import AsyncIterator
from contextlib import asynccontextmanager
from typing import Any

from fastapi import Request
from fastapi.concurrency import run_in_threadpool

from calibration_store import StoreFull, StoreUnavailable
from service.api.request_body import BodyPace, receive_upload
from service.calibration.uploads import UploadWorkspace
from service.errors import ServiceError, UnsupportedMediaType, disk_full_refused
from service.runtime.audit_trail import AuditTrail, Operator
from service.runtime.settings import Settings

_ZIP_TYPES = {"application/zip", "application/x-zip-compressed", "application/octet-stream"}


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
    """Receive a zip body (415 for another type), paced and within the upload limits, into a new
    upload workspace; returns it with the body's sha256 (the caller removes it when done)."""
    content_type = request.headers.get("content-type", "").split(";")[0].strip().lower()
    if content_type not in _ZIP_TYPES:
        raise UnsupportedMediaType(
            f"send the batch as a zip body (Content-Type: application/zip), not {content_type!r}"
        )
    timeout = settings.calibration.upload_read_timeout_seconds
    pace = BodyPace.from_settings(settings, timeout, "CKS_UPLOAD_READ_TIMEOUT_SECONDS")
    with disk_full_refused("the upload"):
        workspace = await run_in_threadpool(UploadWorkspace.create, settings.storage.uploads_dir)
        try:
            saved = await receive_upload(
                request, workspace.archive, settings.calibration.max_upload_bytes, pace
            )
        except BaseException:
            await run_in_threadpool(workspace.remove)
            raise
    return workspace, saved.sha256
