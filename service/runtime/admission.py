"""Admission control for predict: bounded receiving, bounded work, bounded waiting, and a fast
503 beyond.

A request takes a place only once its body has arrived, so a slow client holds no place:
bodies being received count instead against a byte budget (``max_receiving_bytes``, all
requests together, counted as the bytes arrive: a slow client holds only what it sent),
and ``service.api.request_body`` cuts bodies that arrive too slowly. At most ``max_concurrent``
admitted requests decode and infer at once; at most ``max_queued`` more wait for a slot,
each for at most ``timeout`` seconds. A request beyond that is refused with 503 and
``Retry-After`` (before its body is read when every place is already taken), so an overload
costs neither memory (bodies and decoded images of waiting requests) nor unbounded latency:
clients see a clear answer they can back off from instead of a growing queue.
"""

from __future__ import annotations

import asyncio
from collections.abc import AsyncIterator, Callable, Iterator
from contextlib import asynccontextmanager, contextmanager

from service.errors import Unavailable
from service.runtime.metrics import (
    PREDICT_COMPUTING,
    PREDICT_IN_FLIGHT,
    PREDICT_RECEIVING,
    PREDICT_REJECTED,
    PREDICT_WAITING,
)

RETRY_AFTER_SECONDS = 1


class Overloaded(Unavailable):
    title = "Overloaded"

    def __init__(self, detail: str) -> None:
        super().__init__(detail, headers={"Retry-After": str(RETRY_AFTER_SECONDS)})


class Admission:
    """Counts received bytes and admitted requests; one asyncio semaphore hands out the compute
    slots. Used from the event loop only."""

    def __init__(
        self, max_concurrent: int, max_queued: int, timeout: float, max_receiving_bytes: int
    ) -> None:
        self._slots = asyncio.Semaphore(max_concurrent)
        self._max_concurrent, self._max_queued, self._timeout = max_concurrent, max_queued, timeout
        self._max_receiving = max_receiving_bytes
        self._admitted = self._receiving = 0

    @property
    def capacity(self) -> int:
        """Places in all: computing plus waiting."""
        return self._max_concurrent + self._max_queued

    def refuse_if_full(self, places: int = 1) -> None:
        """503 unless ``places`` places (one per image) are free (CKS_MAX_QUEUED_REQUESTS)."""
        if self._admitted + places > self.capacity:
            PREDICT_REJECTED.labels("queue_full").inc()
            needs = f"; this batch needs {places} places, one per image" if places > 1 else ""
            raise Overloaded(
                f"the service is at capacity ({self._max_concurrent} predict requests computing, "
                f"{self._max_queued} waiting; CKS_MAX_CONCURRENT_INFERENCES, CKS_MAX_QUEUED_REQUESTS)"
                f"{needs}: retry after {RETRY_AFTER_SECONDS} s"
            )

    @contextmanager
    def receiving(self) -> Iterator[Callable[[int], None]]:
        """While one body arrives: a function counting its bytes against CKS_MAX_RECEIVING_BYTES
        (503 beyond); they are given back when the body is done with."""
        taken = 0

        def take(count: int) -> None:
            nonlocal taken
            if self._receiving + count > self._max_receiving:
                PREDICT_REJECTED.labels("receiving_budget").inc()
                raise Overloaded(
                    f"the service is receiving {self._receiving} bytes of other predict bodies, and this one"
                    f" would exceed the budget of {self._max_receiving} bytes (CKS_MAX_RECEIVING_BYTES):"
                    f" retry after {RETRY_AFTER_SECONDS} s"
                )
            self._receiving += count
            taken += count
            PREDICT_RECEIVING.inc(count)

        try:
            yield take
        finally:
            self._receiving -= taken
            PREDICT_RECEIVING.dec(taken)

    @asynccontextmanager
    async def admitted(self, places: int = 1) -> AsyncIterator[None]:
        """Take ``places`` places (computing or waiting for a slot; one per image), or fail fast."""
        self.refuse_if_full(places)
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
            if self._slots.locked():
                await asyncio.wait_for(self._slots.acquire(), self._timeout)
            else:  # a free slot is taken at once: no task and timer for a wait that cannot happen
                await self._slots.acquire()
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
