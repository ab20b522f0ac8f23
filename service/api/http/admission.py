"""Admission for predict: bounded places and compute slots, a cap per caller, a fast answer beyond.

A request takes a place once its body has arrived (a slow body holds none; cutting slow clients
is the proxy's job, deploy/haproxy). At most ``slots`` admitted requests compute at once and
``queued`` more wait for a slot, each at most ``timeout`` seconds. Beyond that the answer is 503
with ``Retry-After``: an overload costs neither memory nor unbounded latency.

While more than one caller has asked in the last ``ACTIVE_SECONDS``, one caller (a predict
token's holder, or an address: ``service.api.http.callers``) holds at most ``share`` of the places
and computes on at most ``share`` of the threads that really run at once. A request beyond its
caller's places waits, holding nothing, for one of them to be given back, at most ``timeout``;
then 429 with ``Retry-After``. A flood thus waits instead of coming back at once, and a caller
that asks little finds a slot free. A caller alone may use every place.
"""

from __future__ import annotations

import asyncio
import time
from collections import Counter
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager

from service.errors import TooManyRequests, Unavailable
from service.infra.metrics import PREDICT_COMPUTING, PREDICT_IN_FLIGHT, PREDICT_REJECTED, PREDICT_WAITING

RETRY_AFTER_SECONDS = 1
#: How long a request waits for a compute slot, or for a place of its caller's share.
QUEUE_TIMEOUT_SECONDS = 10.0
#: A caller counts as active this long after its last predict request.
ACTIVE_SECONDS = 30.0
_RETRY = {"Retry-After": str(RETRY_AFTER_SECONDS)}


class Overloaded(Unavailable):
    title = "Overloaded"


class Admission:
    """Places, compute slots and each caller's share of them; used from the event loop only."""

    def __init__(
        self,
        slots: int,
        queued: int,
        share: float = 1.0,
        threads: int | None = None,
        timeout: float = QUEUE_TIMEOUT_SECONDS,
    ) -> None:
        """``threads``: the compute threads that really run at once (the fewer of the slots and
        the cores), of which a caller gets ``share`` while others are active."""
        self.capacity = slots + queued
        self._slots, self._queued, self._share, self._timeout = slots, queued, share, timeout
        self._caller_places = max(1, int(self.capacity * share))
        self._caller_slots = max(1, int(min(slots, threads or slots) * share))
        self._admitted, self._free_slots = 0, slots
        self._held: Counter[str] = Counter()  # places per caller
        self._computing: Counter[str] = Counter()  # slots per caller
        self._slot_waiters: list[tuple[str, asyncio.Future[None]]] = []  # oldest first
        self._place_waiters: dict[str, list[asyncio.Future[None]]] = {}
        self._asked: dict[str, float] = {}  # caller -> when it last asked, least recent first

    async def wait_for_place(self, caller: str, places: int = 1) -> None:
        """Before a body is received: while ``caller`` holds its share, wait (holding nothing)
        for one of its places, at most the timeout; then as ``refuse_if_full``."""
        self._note(caller)
        if self._over_share(caller, places) and places <= self._caller_places:
            freed = asyncio.get_running_loop().create_future()
            self._place_waiters.setdefault(caller, []).append(freed)
            try:
                async with asyncio.timeout(self._timeout):
                    await freed
            except TimeoutError:
                pass  # refused below with 429
            finally:
                self._stop_waiting(caller, freed)
        self.refuse_if_full(caller, places)

    def refuse_if_full(self, caller: str, places: int = 1) -> None:
        """429 when ``caller`` would hold more than its share while others are active; 503 unless
        ``places`` places (one per image) are free."""
        self._note(caller)
        needs = f"; this batch needs {places} places, one per image" if places > 1 else ""
        if self._over_share(caller, places):
            PREDICT_REJECTED.labels("client_share").inc()
            raise TooManyRequests(
                f"this caller ({caller}) already holds {self._held[caller]} of the {self._caller_places}"
                f" predict places one caller may hold while others are served (CKS_CLIENT_SHARE"
                f" {self._share:g} of {self.capacity}){needs}: retry after {RETRY_AFTER_SECONDS} s",
                headers=_RETRY,
            )
        if self._admitted + places > self.capacity:
            PREDICT_REJECTED.labels("queue_full").inc()
            raise Overloaded(
                f"the service is at capacity ({self._slots} predict requests computing, {self._queued}"
                f" waiting; CKS_MAX_CONCURRENT_INFERENCES, CKS_MAX_QUEUED_REQUESTS){needs}: retry after"
                f" {RETRY_AFTER_SECONDS} s",
                headers=_RETRY,
            )

    @asynccontextmanager
    async def admitted(self, caller: str, places: int = 1) -> AsyncIterator[None]:
        """Take ``places`` places (computing or waiting for a slot; one per image), or fail fast."""
        self.refuse_if_full(caller, places)
        self._admitted += places
        self._held[caller] += places
        PREDICT_IN_FLIGHT.inc(places)
        try:
            yield
        finally:
            self._admitted -= places
            _drop(self._held, caller, places)
            PREDICT_IN_FLIGHT.dec(places)
            for freed in self._place_waiters.get(caller, [])[:places]:
                freed.done() or freed.set_result(None)

    @asynccontextmanager
    async def slot(self, caller: str) -> AsyncIterator[None]:
        """A compute slot, waited for at most the timeout (then 503)."""
        self._note(caller)
        granted = asyncio.get_running_loop().create_future()
        self._slot_waiters.append((caller, granted))
        self._grant()
        PREDICT_WAITING.inc()
        try:
            async with asyncio.timeout(self._timeout):
                await granted
        except BaseException as error:
            if granted.done() and not granted.cancelled():  # granted just as the wait ended
                self._give_back(caller)
            elif (caller, granted) in self._slot_waiters:  # else a grant already dropped it
                self._slot_waiters.remove((caller, granted))
            if not isinstance(error, TimeoutError):
                raise
            PREDICT_REJECTED.labels("queue_timeout").inc()
            raise Overloaded(
                f"no compute slot became free within {self._timeout:g} s: retry after"
                f" {RETRY_AFTER_SECONDS} s",
                headers=_RETRY,
            ) from None
        finally:
            PREDICT_WAITING.dec()
        PREDICT_COMPUTING.inc()
        try:
            yield
        finally:
            PREDICT_COMPUTING.dec()
            self._give_back(caller)

    def _give_back(self, caller: str) -> None:
        _drop(self._computing, caller, 1)
        self._free_slots += 1
        self._grant()

    def _grant(self) -> None:
        """Free slots to the oldest waiting requests whose callers are within their share."""
        shared = self._shared()
        for caller, granted in list(self._slot_waiters):
            if not self._free_slots:
                return
            if granted.done():  # its request was cancelled (a shutdown cancels them all at once)
                self._slot_waiters.remove((caller, granted))
                continue
            if shared and self._computing[caller] >= self._caller_slots:
                continue
            self._slot_waiters.remove((caller, granted))
            self._free_slots -= 1
            self._computing[caller] += 1
            granted.set_result(None)

    def _over_share(self, caller: str, places: int) -> bool:
        return self._held[caller] + places > self._caller_places and self._shared()

    def _shared(self) -> bool:
        """Whether more than one caller is active: shares apply only then."""
        return len(self._asked) > 1

    def _note(self, caller: str) -> None:
        """Remember that ``caller`` asked now; forget the callers quiet for ACTIVE_SECONDS."""
        now = time.monotonic()
        self._asked.pop(caller, None)
        self._asked[caller] = now
        while now - self._asked[oldest := next(iter(self._asked))] > ACTIVE_SECONDS:
            del self._asked[oldest]

    def _stop_waiting(self, caller: str, freed: asyncio.Future[None]) -> None:
        waiters = self._place_waiters[caller]
        waiters.remove(freed)
        if not waiters:
            del self._place_waiters[caller]


def _drop(counter: Counter[str], key: str, count: int) -> None:
    """Take ``count`` from ``key``, forgetting it at zero (counters of active callers stay small)."""
    counter[key] -= count
    if not counter[key]:
        del counter[key]
