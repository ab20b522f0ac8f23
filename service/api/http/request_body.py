"""Reading request bodies within limits of size, time and pace, before anything is parsed.

A body must arrive whole within its timeout and, once its grace period is over, at an
average of at least ``CKS_MIN_BODY_BYTES_PER_SECOND``: a client trickling a few bytes a
second is cut with 408 after the grace period, not after the whole timeout.
"""

from __future__ import annotations

import asyncio
from collections.abc import AsyncIterator, Callable
from contextlib import aclosing
from dataclasses import dataclass

from fastapi import Request

from service.errors import PayloadTooLarge, RequestTimeout
from service.infra.settings import Settings


@dataclass(frozen=True)
class BodyPace:
    """How long a body may take: all of it within ``timeout_s`` (setting ``timeout_setting``),
    and after ``grace_s`` at least ``min_rate`` bytes per second on average since it began."""

    timeout_s: float
    timeout_setting: str
    min_rate: float
    grace_s: float

    @classmethod
    def from_settings(cls, settings: Settings, timeout_s: float, timeout_setting: str) -> BodyPace:
        rate, grace = settings.server.min_body_bytes_per_second, settings.server.body_rate_grace_seconds
        return cls(timeout_s, timeout_setting, rate, grace)

    def refusal(self, received: int, elapsed: float, too_slow: bool) -> RequestTimeout:
        if too_slow:
            detail = (
                f"the request body arrived at {received / elapsed:.0f} bytes/s on average, below the minimum"
                f" of {self.min_rate:g} bytes/s (CKS_MIN_BODY_BYTES_PER_SECOND, required after"
                f" CKS_BODY_RATE_GRACE_SECONDS = {self.grace_s:g} s)"
            )
        else:
            detail = f"the request body did not arrive within {self.timeout_s:g} s ({self.timeout_setting})"
        return RequestTimeout(detail, headers={"Connection": "close"})


async def paced_chunks(request: Request, pace: BodyPace) -> AsyncIterator[bytes]:
    """The body's chunks as they arrive; ``RequestTimeout`` as soon as it is late or too slow."""
    loop = asyncio.get_running_loop()
    start = loop.time()
    cutoff, received = start + pace.timeout_s, 0
    async with aclosing(request.stream()) as chunks:
        while True:
            too_slow_at = start + pace.grace_s + received / pace.min_rate
            try:
                async with asyncio.timeout_at(min(cutoff, too_slow_at)):
                    chunk = await anext(chunks, None)
            except TimeoutError:
                raise pace.refusal(received, loop.time() - start, too_slow=too_slow_at < cutoff) from None
            if chunk is None:
                return
            received += len(chunk)
            yield chunk


async def read_limited_body(
    request: Request, limit: int, setting: str, pace: BodyPace, count: Callable[[int], None]
) -> bytes:
    """The whole body, paced; 413 as soon as it exceeds ``limit`` bytes. ``count`` is told each
    chunk's size as it arrives (and may refuse it)."""
    declared = request.headers.get("content-length")
    if declared and declared.isdigit() and int(declared) > limit:
        raise PayloadTooLarge(f"the request body is {declared} bytes; the limit is {limit} ({setting})")
    chunks, size = [], 0
    async with aclosing(paced_chunks(request, pace)) as stream:
        async for chunk in stream:
            size += len(chunk)
            if size > limit:
                raise PayloadTooLarge(f"the request body exceeds {limit} bytes ({setting})")
            count(len(chunk))
            chunks.append(chunk)
    body = b"".join(chunks)
    request._body = body  # lets request.form() parse what was already read
    return body
