"""Admission control for predict: bounded receiving, bounded work, bounded waiting, and a fast
503 beyond.

A request takes a place only once its body has arrived, so a slow client holds no place:
bodies being received count instead against a byte budget (``max_receiving_bytes``, all
requests together, counted as the bytes arrive: a slow client holds only what it sent),
and ``service.api.http.request_body`` cuts bodies that arrive too slowly. At most ``max_concurrent``
admitted requests decode and infer at once; at most ``max_queued`` more wait for a slot,
each for at most ``timeout`` seconds. A request beyond that is refused with 503 and
``Retry-After`` (before its body is read when every place is already taken), so an overload
costs neither memory (bodies and decoded images of waiting requests) nor unbounded latency:
clients see a clear answer they can back off from instead of a growing queue.

Fair shares: while more than one client has asked in the last ``ACTIVE_SECONDS``, one client
(``service.api.http.clients``) may hold at most ``max(1, places x share)`` of the places
(``client_share``, CKS_CLIENT_SHARE) and compute on at most ``max(1, threads x share)`` slots
(threads: the slots that really run at once, the fewer of the slots and CKS_CPU_WORKERS); a
request beyond its client's places is refused with 429 and ``Retry-After`` at once, and a free
slot goes to the waiting request whose client computes least (the oldest first). So one
client's flood is refused while another client within its share keeps being served; a client
alone may use every place.
"""

from __future__ import annotations

import asyncio
import time
from collections import Counter
from collections.abc import AsyncIterator, Callable, Iterator
from contextlib import asynccontextmanager, contextmanager

from service.errors import TooManyRequests, Unavailable
from service.infra.metrics import (
    PREDICT_COMPUTING,
    PREDICT_IN_FLIGHT,
    PREDICT_RECEIVING,
    PREDICT_REJECTED,
    PREDICT_WAITING,
)

RETRY_AFTER_SECONDS = 1
#: A client counts as active this long after its last predict request (admitted or not).
ACTIVE_SECONDS = 30.0


class Overloaded(Unavailable):
    title = "Overloaded"

    def __init__(self, detail: str) -> None:
        super().__init__(detail, headers={"Retry-After": str(RETRY_AFTER_SECONDS)})


class OverShare(TooManyRequests):
    def __init__(self, detail: str) -> None:
        super().__init__(detail, headers={"Retry-After": str(RETRY_AFTER_SECONDS)})


class Admission:
    """Counts received bytes and admitted requests, and hands out the compute slots, per client.
    Used from the event loop only."""

    def __init__(
        self,
        max_concurrent: int,
        max_queued: int,
        timeout: float,
        max_receiving_bytes: int,
        client_share: float = 1.0,
        threads: int | None = None,
    ) -> None:
        self._max_concurrent, self._max_queued, self._timeout = max_concurrent, max_queued, timeout
        self._max_receiving = max_receiving_bytes
        self._admitted = self._receiving = 0
        self._share = client_share
        self._client_places = max(1, int(self.capacity * client_share))
        self._client_slots = max(1, int(min(max_concurrent, threads or max_concurrent) * client_share))
        self._held: Counter[str] = Counter()  # places per client
        self._computing: Counter[str] = Counter()  # slots per client
        self._free_slots = max_concurrent
        self._waiting: list[tuple[str, asyncio.Future[None]]] = []  # oldest first
        self._asked: dict[str, float] = {}  # client -> when it last asked, least recent first

    @property
    def capacity(self) -> int:
        """Places in all: computing plus waiting."""
        return self._max_concurrent + self._max_queued

    def refuse_if_full(self, places: int = 1, client: str = "") -> None:
        """429 when ``client`` would hold more than its share of the places while others are
        active (CKS_CLIENT_SHARE); 503 unless ``places`` places (one per image) are free
        (CKS_MAX_QUEUED_REQUESTS)."""
        self._note(client)
        needs = f"; this batch needs {places} places, one per image" if places > 1 else ""
        limited = self._client_places < self.capacity and self._shared()
        if limited and self._held[client] + places > self._client_places:
            PREDICT_REJECTED.labels("client_share").inc()
            raise OverShare(
                f"this client ({client}) already holds {self._held[client]} of the"
                f" {self._client_places} predict places one client may hold while others are"
                f" served (CKS_CLIENT_SHARE {self._share:g} of {self.capacity}){needs}:"
                f" retry after {RETRY_AFTER_SECONDS} s"
            )
        if self._admitted + places > self.capacity:
            PREDICT_REJECTED.labels("queue_full").inc()
            raise Overloaded(
                f"the service is at capacity ({self._max_concurrent} predict requests computing, "
                f"{self._max_queued} waiting; CKS_MAX_CONCURRENT_INFERENCES, CKS_MAX_QUEUED_REQUESTS)"
                f"{needs}: retry after {RETRY_AFTER_SECONDS} s"
            )

    def _note(self, client: str) -> None:
        """Remember that ``client`` asked now; forget the clients quiet for ACTIVE_SECONDS."""
        now = time.monotonic()
        self._asked.pop(client, None)
        self._asked[client] = now
        while now - self._asked[oldest := next(iter(self._asked))] > ACTIVE_SECONDS:
            del self._asked[oldest]

    def _shared(self) -> bool:
        """Whether more than one client is active: shares apply only then."""
        return len(self._asked) > 1

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
    async def admitted(self, places: int = 1, client: str = "") -> AsyncIterator[None]:
        """Take ``places`` places (computing or waiting for a slot; one per image), or fail fast."""
        self.refuse_if_full(places, client)
        self._admitted += places
        self._held[client] += places
        PREDICT_IN_FLIGHT.inc(places)
        try:
            yield
        finally:
            self._admitted -= places
            self._held[client] -= places
            if not self._held[client]:
                del self._held[client]
            PREDICT_IN_FLIGHT.dec(places)

    @asynccontextmanager
    async def slot(self, client: str = "") -> AsyncIterator[None]:
        """A compute slot, waited for at most the queue timeout (CKS_QUEUE_TIMEOUT_SECONDS)."""
        PREDICT_WAITING.inc()
        try:
            await self._take_slot(client)
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
            self._give_back(client)

    async def _take_slot(self, client: str) -> None:
        granted = asyncio.get_running_loop().create_future()
        waiter = (client, granted)
        self._waiting.append(waiter)
        self._grant()
        if granted.done():  # a free slot is taken at once: no timer for a wait that cannot happen
            return
        try:
            async with asyncio.timeout(self._timeout):
                await granted
        except BaseException:
            if granted.done() and not granted.cancelled():  # granted just as the wait ended
                self._give_back(client)
            elif waiter in self._waiting:
                self._waiting.remove(waiter)
            raise

    def _give_back(self, client: str) -> None:
        self._computing[client] -= 1
        if not self._computing[client]:
            del self._computing[client]
        self._free_slots += 1
        self._grant()

    def _grant(self) -> None:
        """Free slots to waiting requests: the one whose client computes least, oldest first; a
        client at its share of the slots waits while others are active."""
        self._waiting = [waiter for waiter in self._waiting if not waiter[1].done()]
        while self._free_slots:
            shared = self._shared()
            eligible = [
                waiter
                for waiter in self._waiting
                if not shared or self._computing[waiter[0]] < self._client_slots
            ]
            if not eligible:
                return
            client, granted = min(eligible, key=lambda waiter: self._computing[waiter[0]])
            self._waiting.remove((client, granted))
            self._free_slots -= 1
            self._computing[client] += 1
            granted.set_result(None)
