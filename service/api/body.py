"""Reading request bodies with a size limit, before anything is parsed."""

from __future__ import annotations

from pathlib import Path

from fastapi import Request
from fastapi.concurrency import run_in_threadpool

from service.calibration.archive import SavedUpload, UploadSink
from service.errors import PayloadTooLarge

_FLUSH_BYTES = 1 << 20


async def read_limited_body(request: Request, limit: int, setting: str) -> bytes:
    """The whole body, refusing with 413 as soon as it exceeds ``limit`` bytes."""
    declared = request.headers.get("content-length")
    if declared and declared.isdigit() and int(declared) > limit:
        raise PayloadTooLarge(f"the request body is {declared} bytes; the limit is {limit} ({setting})")
    chunks, size = [], 0
    async for chunk in request.stream():
        size += len(chunk)
        if size > limit:
            raise PayloadTooLarge(f"the request body exceeds {limit} bytes ({setting})")
        chunks.append(chunk)
    body = b"".join(chunks)
    request._body = body  # lets request.form() parse what was already read
    return body


async def receive_upload(request: Request, dest: Path, limit: int) -> SavedUpload:
    """Stream the body to ``dest`` (never whole in memory), hashing it; 413 beyond ``limit``."""
    sink = await run_in_threadpool(UploadSink, dest, limit)
    pending: list[bytes] = []
    try:
        async for chunk in request.stream():
            pending.append(chunk)
            if sum(map(len, pending)) >= _FLUSH_BYTES:
                await run_in_threadpool(sink.write, b"".join(pending))
                pending.clear()
        await run_in_threadpool(sink.write, b"".join(pending))
    except BaseException:
        sink.abort()
        raise
    return sink.finish()
