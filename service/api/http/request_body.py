"""Reading request bodies within a size limit and a time limit, before anything is parsed.

Cutting slow clients early (a minimum rate, slow heads) is the proxy's job (deploy/haproxy); here
a body that has not arrived whole within its time limit is answered 408, so a client that never
finishes holds its connection for a bounded time even without a proxy.
"""

from __future__ import annotations

import asyncio
from collections.abc import AsyncIterator
from contextlib import aclosing

from fastapi import Request

from service.errors import PayloadTooLarge, RequestTimeout

#: How long a predict body may take to arrive; a calibration upload, ``UPLOAD_TIMEOUT_SECONDS``.
PREDICT_TIMEOUT_SECONDS = 30.0
UPLOAD_TIMEOUT_SECONDS = 3600.0


async def timed_chunks(request: Request, timeout_s: float) -> AsyncIterator[bytes]:
    """The body's chunks as they arrive; ``RequestTimeout`` once it is later than ``timeout_s``."""
    deadline = asyncio.get_running_loop().time() + timeout_s
    async with aclosing(request.stream()) as chunks:
        while True:
            try:
                async with asyncio.timeout_at(deadline):
                    chunk = await anext(chunks, None)
            except TimeoutError:
                raise RequestTimeout(
                    f"the request body did not arrive within {timeout_s:g} s", headers={"Connection": "close"}
                ) from None
            if chunk is None:
                return
            yield chunk


async def read_limited_body(request: Request, limit: int, setting: str) -> bytes:
    """The whole body, within ``PREDICT_TIMEOUT_SECONDS``; 413 as soon as it exceeds ``limit`` bytes."""
    declared = request.headers.get("content-length")
    if declared and declared.isdigit() and int(declared) > limit:
        raise PayloadTooLarge(f"the request body is {declared} bytes; the limit is {limit} ({setting})")
    chunks, size = [], 0
    async with aclosing(timed_chunks(request, PREDICT_TIMEOUT_SECONDS)) as stream:
        async for chunk in stream:
            size += len(chunk)
            if size > limit:
                raise PayloadTooLarge(f"the request body exceeds {limit} bytes ({setting})")
            chunks.append(chunk)
    body = b"".join(chunks)
    request._body = body  # lets request.form() parse what was already read
    return body
