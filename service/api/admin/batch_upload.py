"""A labeled batch as the admin API receives it (calibration uploads, coverage audits): the route, its
query parameters and documentation, the zip received for a job, every refusal in the audit trail."""

from __future__ import annotations

from collections.abc import AsyncIterator, Callable
from contextlib import AbstractAsyncContextManager, aclosing, asynccontextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Annotated, Any, TypeVar

from fastapi import APIRouter, Depends, Query, Request, Response
from fastapi.concurrency import run_in_threadpool
from fastapi.types import DecoratedCallable

from calibration_store import JobRecord, StoreFull, StoreUnavailable
from service.api.admin.admin_presenters import job_out
from service.api.admin.admin_schemas import JobOut
from service.api.admin.job_links import JOB_LINKS
from service.api.deps import Admin, Config, Trail
from service.api.http.multipart_file import FilePart
from service.api.http.request_body import UPLOAD_TIMEOUT_SECONDS, timed_chunks
from service.calibration.archive import SavedUpload, UploadSink
from service.calibration.uploads import UploadWorkspace
from service.errors import ServiceError, disk_full_refused
from service.infra.audit_trail import AuditTrail, Operator
from service.infra.settings import Settings

Options = TypeVar("Options")
_FLUSH_BYTES = 1 << 20

ZIP_PART = "file"  # the zip's part name when the batch comes as multipart/form-data
_BYTES = {"type": "string", "format": "binary"}
_ZIP_FORM = {
    "type": "object",
    "required": [ZIP_PART],
    "properties": {ZIP_PART: {**_BYTES, "description": "the zip"}},
}
_RECEIVED = {
    "408": "The body did not arrive within an hour",
    "413": "The zip, its files or its unzipped size exceed the limits",
}


@asynccontextmanager
async def refusals_audited(
    trail: AuditTrail, operator: Operator, action: str, context: dict | None = None, **fields: Any
) -> AsyncIterator[None]:
    """Append every refusal of an admin action to the audit trail before it is answered, then let
    it through; one the store caused (unreachable, locked, full) is appended once the store can."""
    try:
        yield
    except ServiceError as error:
        refused = {**(context or {}), "status": error.status, "detail": error.detail}
        details = {**refused, "errors": error.errors[:10]}
        await run_in_threadpool(trail.record, operator, action, "refused", details=details, **fields)
        raise
    except StoreUnavailable as error:
        status = 507 if isinstance(error, StoreFull) else 503
        details = {**(context or {}), "status": status, "detail": str(error), "errors": []}
        trail.record_later(operator, action, "refused", details=details, **fields)
        raise


BatchName = Annotated[str | None, Query(max_length=200, description="batch name (default: upload-<sha256>)")]
Note = Annotated[str, Query(max_length=2000)]


def _rejected_share(what: str) -> Any:
    """The ``max_rejected_share`` parameter of an upload whose failure is ``what``'s."""
    description = (
        f"share of instances the box rule or strict decoding may reject before {what} fails (default 0: none)"
    )
    return Annotated[float | None, Query(ge=0, le=1, description=description)]


BatchRejectedShare = _rejected_share("the batch")
AuditRejectedShare = _rejected_share("the audit")


def upload_route(
    router: APIRouter,
    paths: tuple[str, str],
    summary: str,
    batch: str,
    responses: dict[str, str],
    parameters: tuple[dict[str, Any], ...] = (),
) -> Callable[[DecoratedCallable], DecoratedCallable]:
    """An upload route (202 with its job), registered twice as client generators need: the raw zip of a
    ``batch`` on ``paths[0]`` (octet-stream), the form on ``paths[1]`` (``<name>_form``)."""
    refusals = {status: {"description": text} for status, text in {**_RECEIVED, **responses}.items()}
    raw = _zip_body("The raw zip", batch, "application/octet-stream", _BYTES)
    form = _zip_body("The zip as the part 'file'", batch, "multipart/form-data", _ZIP_FORM)
    route = {"status_code": 202, "responses": {202: {"links": JOB_LINKS}}, "response_model": JobOut}

    def register(endpoint: DecoratedCallable) -> DecoratedCallable:
        def post(path: str, body: dict[str, Any], name: str | None, summary: str) -> None:
            extra = {"requestBody": body, "responses": refusals, "parameters": list(parameters)}
            router.post(path, name=name, summary=summary, openapi_extra=extra, **route)(endpoint)

        post(paths[0], raw, None, summary)
        post(paths[1], form, f"{endpoint.__name__}_form", f"{summary} (multipart/form-data)")
        return endpoint

    return register


def _zip_body(how: str, batch: str, media: str, schema: dict[str, Any]) -> dict[str, Any]:
    description = f"{how}. A zip of a COCO-keypoints batch{batch}"
    return {"required": True, "content": {media: {"schema": schema}}, "description": description}


@dataclass(frozen=True)
class UploadCall:
    """An upload route's call: the zip it receives and who sends it (``Upload``)."""

    request: Request
    response: Response
    trail: AuditTrail
    settings: Settings
    who: Operator

    def audited(self, action: str) -> AbstractAsyncContextManager[None]:
        """Every refusal inside, ``action``'s in the audit trail (``refusals_audited``)."""
        return refusals_audited(self.trail, self.who, action)

    async def start(
        self, options: Options, accept: Callable[[UploadWorkspace, str, Options, Operator], JobRecord]
    ) -> JobOut:
        """Receive the zip, hand it with ``options`` to ``accept``: the job it starts, with its Location."""
        workspace, sha256 = await receive_batch_zip(self.request, self.settings)
        job = await run_in_threadpool(accept, workspace, sha256, options, self.who)
        self.response.headers["Location"] = f"/v1/admin/jobs/{job.id}"
        return job_out(job)


async def upload_call(
    request: Request, response: Response, trail: Trail, settings: Config, who: Admin
) -> UploadCall:
    return UploadCall(request, response, trail, settings, who)


Upload = Annotated[UploadCall, Depends(upload_call)]


async def receive_batch_zip(request: Request, settings: Settings) -> tuple[UploadWorkspace, str]:
    """The zip (raw, or a form's part 'file') received in time and within the limits into a new upload
    workspace, and its sha256. Any type but multipart/form-data is the raw zip: judged by its bytes."""
    content_type = request.headers.get("content-type", "").split(";")[0].strip().lower()
    part = ZIP_PART if content_type == "multipart/form-data" else None
    with disk_full_refused("the upload"):
        workspace = await run_in_threadpool(UploadWorkspace.create, settings.storage.uploads_dir)
        try:
            limit = settings.calibration.max_upload_bytes
            saved = await receive_upload(request, workspace.archive, limit, part)
        except BaseException:
            await run_in_threadpool(workspace.remove)
            raise
    return workspace, saved.sha256


async def receive_upload(request: Request, dest: Path, limit: int, part: str | None = None) -> SavedUpload:
    """Stream the body (with ``part``: only that form part's bytes), within UPLOAD_TIMEOUT_SECONDS, to
    ``dest`` (never whole in memory), hashing it; 413 beyond ``limit``."""
    sink = await run_in_threadpool(UploadSink, dest, limit)
    pending = bytearray()
    try:
        form = None if part is None else FilePart(request.headers.get("content-type", ""), part, sink.write)
        write = sink.write if form is None else form.write
        async with aclosing(timed_chunks(request, UPLOAD_TIMEOUT_SECONDS)) as stream:
            async for chunk in stream:
                pending += chunk
                if len(pending) >= _FLUSH_BYTES:
                    await run_in_threadpool(write, bytes(pending))
                    pending.clear()
        await run_in_threadpool(write, bytes(pending))
        if form is not None:
            form.finish()
    except BaseException:
        sink.abort()
        raise
    return sink.finish()
