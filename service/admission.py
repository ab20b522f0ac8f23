"""Admission control for predict: bounded work, bounded waiting, and a fast 503 beyond.

At most ``max_concurrent`` requests decode and infer at once; at most ``max_queued``
more wait for a slot, each for at most ``timeout`` seconds. A request beyond that is
refused at once with 503 and ``Retry-After``, before its body is read, so an overload
costs neither memory (bodies and decoded images of waiting requests) nor unbounded
latency: clients see a clear answer they can back off from instead of a growing queue.
"""

from __future__ import annotations

import asyncio
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager

from service.errors import Unavailable
from service.metrics import PREDICT_COMPUTING, PREDICT_IN_FLIGHT, PREDICT_REJECTED, PREDICT_WAITING

RETRY_AFTER_SECONDS = 1


class Overloaded(Unavailable):
    title = "Overloaded"

    def __init__(self, detail: str) -> None:
        super().__init__(detail, headers={"Retry-After": str(RETRY_AFTER_SECONDS)})


class Admission:
    """Counts admitted requests; one asyncio semaphore hands out the compute slots."""

    def __init__(self, max_concurrent: int, max_queued: int, timeout: float) -> None:
        self._slots = asyncio.Semaphore(max_concurrent)
        self._max_concurrent, self._max_queued, self._timeout = max_concurrent, max_queued, timeout
        self._admitted = 0

    @property
    def capacity(self) -> int:
        """Places in all: computing plus waiting."""
        return self._max_concurrent + self._max_queued

    @asynccontextmanager
    async def admitted(self, places: int = 1) -> AsyncIterator[None]:
        """Enter the queue with ``places`` places (one per image) or fail fast (CKS_MAX_QUEUED_REQUESTS)."""
        if self._admitted + places > self.capacity:
            PREDICT_REJECTED.labels("queue_full").inc()
            needs = f"; this batch needs {places} more places, one per image" if places > 1 else ""
            raise Overloaded(
                f"the service is at capacity ({self._max_concurrent} predict requests computing, "
                f"{self._max_queued} waiting; CKS_MAX_CONCURRENT_INFERENCES, CKS_MAX_QUEUED_REQUESTS)"
                f"{needs}: retry after {RETRY_AFTER_SECONDS} s"
            )
        self._admitted += places
        PREDICT_IN_FLIGHT.inc(places)
        try:
            yield
        finally:
            self._admitted -= places
            PREDICT_IN_FLIGHT.dec(places)

    @asynccontextmanager
    async def slot(self) -> AsyncIterator[None]:
        """A compute slot, waited for at most the queue timeout (CKS_QUEUE_TIMEOUT_SECONDS)."""
        PREDICT_WAITING.inc()
        try:
            await asyncio.wait_for(self._slots.acquire(), self._timeout)
        except TimeoutError:
            PREDICT_REJECTED.labels("queue_timeout").inc()
            raise Overloaded(
                f"no compute slot became free within {self._timeout:g} s (CKS_QUEUE_TIMEOUT_SECONDS): "
                f"retry after {RETRY_AFTER_SECONDS} s"
            ) from None
        finally:
            PREDICT_WAITING.dec()
        PREDICT_COMPUTING.inc()
        try:
            yield
        finally:
            PREDICT_COMPUTING.dec()
            self._slots.release()
