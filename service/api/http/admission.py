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
(threads: the slots that really run at once, the fewer of the slots, CKS_CPU_WORKERS and the
usable cores). A request beyond its client's places waits, before its body is received and
holding nothing, for one of its client's places, at most the queue timeout; then it is refused
with 429 and ``Retry-After`` (a flood that ignores Retry-After would otherwise come back at once,
and the event loop would spend itself refusing). A free slot goes to the waiting request whose
client has used the least compute (start-time fair queueing: each client's virtual time
advances by the seconds its requests hold a slot, and a client that was idle starts at the
virtual time now, so it goes ahead of every client with work waiting; the oldest first among
equals). So one client's flood waits beyond its share, behind a client
that asks little; a client alone may use every place. With several workers, a board in shared
memory (``service.infra.client_board``) tells each which clients the others serve and on how
many slots, so that whether shares apply and a client's slots hold for the process group.
"""

from __future__ import annotations

import asyncio
import time
from collections import Counter, deque
from collections.abc import AsyncIterator, Callable, Iterator
from contextlib import asynccontextmanager, contextmanager

from service.errors import TooManyRequests, Unavailable
from service.infra.client_board import ClientBoard
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
#: How often a request held back by its client's slots in other workers looks again.
RECHECK_SECONDS = 0.02


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
        board: ClientBoard | None = None,
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
        self._board = board  # the clients of the other workers (CKS_WORKERS), where there is one
        self._rechecking = False  # a look at the board's slots is due
        self._clock = 0.0  # virtual time: the start of the last slot granted
        self._used: dict[str, float] = {}  # client -> its virtual time (compute seconds charged)
        self._cost: dict[str, float] = {}  # client -> seconds its last slot was held (the next's guess)
        self._place_waiters: dict[str, deque[asyncio.Future[None]]] = {}  # oldest first

    @property
    def capacity(self) -> int:
        """Places in all: computing plus waiting."""
        return self._max_concurrent + self._max_queued

    async def wait_for_place(self, places: int = 1, client: str = "") -> None:
        """Before a body is received: while ``client`` holds its share of the places, wait (holding
        nothing) until one of its own places is given back, its requests in order, at most the
        queue timeout; then as ``refuse_if_full``. A flood thus waits instead of coming back at once."""
        self._note(client)
        waits = self._over_share(client, places) or client in self._place_waiters
        if waits and places <= self._client_places:  # a batch that can never fit is refused at once
            await self._queue_for_place(client)
        self.refuse_if_full(places, client)

    async def _queue_for_place(self, client: str) -> None:
        freed = asyncio.get_running_loop().create_future()
        waiters = self._place_waiters.setdefault(client, deque())
        waiters.append(freed)
        try:
            async with asyncio.timeout(self._timeout):
                await freed
        except TimeoutError:
            pass  # refused below with 429
        finally:
            if freed in waiters:
                waiters.remove(freed)
            if not waiters and self._place_waiters.get(client) is waiters:
                del self._place_waiters[client]

    def _over_share(self, client: str, places: int) -> bool:
        limited = self._client_places < self.capacity and self._shared()
        return limited and self._held[client] + places > self._client_places

    def refuse_if_full(self, places: int = 1, client: str = "") -> None:
        """429 when ``client`` would hold more than its share of the places while others are
        active (CKS_CLIENT_SHARE); 503 unless ``places`` places (one per image) are free
        (CKS_MAX_QUEUED_REQUESTS)."""
        self._note(client)
        needs = f"; this batch needs {places} places, one per image" if places > 1 else ""
        if self._over_share(client, places):
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
        if self._board is not None:
            self._board.note(client)
        self._asked.pop(client, None)
        self._asked[client] = now
        while now - self._asked[oldest := next(iter(self._asked))] > ACTIVE_SECONDS:
            del self._asked[oldest]
            self._used.pop(oldest, None)
            self._cost.pop(oldest, None)

    def _shared(self) -> bool:
        """Whether more than one client is active in this worker or any other: shares apply only then."""
        board = self._board
        return len(self._asked) > 1 or (board is not None and board.several_since(ACTIVE_SECONDS))

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
            self._hand_over(client)

    def _hand_over(self, client: str) -> None:
        """A place ``client`` gave back goes to its oldest request waiting for one."""
        waiters = self._place_waiters.get(client, deque())
        while waiters:
            if not (freed := waiters.popleft()).done():  # not one whose wait just ended
                freed.set_result(None)
                return

    @asynccontextmanager
    async def slot(self, client: str = "") -> AsyncIterator[bool]:
        """A compute slot, waited for at most the queue timeout (CKS_QUEUE_TIMEOUT_SECONDS); yields
        whether to compute at background priority (``service.infra.cpu_priority``): while others
        are served, a client holding several places, so that the kernel gives a one-at-a-time
        client's request the cores first."""
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
        background = self._held[client] > 1 and self._shared()
        PREDICT_COMPUTING.inc()
        started = time.monotonic()
        try:
            yield background
        finally:
            PREDICT_COMPUTING.dec()
            self._charge(client, time.monotonic() - started)
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
        if self._board is not None:
            self._board.note(client, computing=-1)
        self._free_slots += 1
        self._grant()

    def _recheck(self) -> None:
        self._rechecking = False
        self._grant()

    def _computing_anywhere(self, client: str) -> int:
        """The slots ``client`` computes on, in every worker where there is a board."""
        here = self._computing[client]
        return max(here, self._board.computing(client)) if self._board is not None else here

    def _charge(self, client: str, seconds: float) -> None:
        """Correct the guess charged when ``client``'s slot was granted by what it really held."""
        if client in self._used:
            self._used[client] += seconds - self._cost.get(client, 0.0)
        self._cost[client] = seconds

    def _virtual_time(self, client: str) -> float:
        return max(self._used.get(client, 0.0), self._clock)

    def _grant(self) -> None:
        """Free slots to waiting requests: the one whose client has used least (its virtual time),
        oldest first; a client at its share of the slots waits while others are active."""
        self._waiting = [waiter for waiter in self._waiting if not waiter[1].done()]
        while self._free_slots:
            shared = self._shared()
            clients = {client for client, _ in self._waiting} if shared else set()
            computing = {client: self._computing_anywhere(client) for client in clients}
            eligible = [
                waiter for waiter in self._waiting if not shared or computing[waiter[0]] < self._client_slots
            ]
            if not eligible:
                if self._waiting and self._board is not None and not self._rechecking:
                    self._rechecking = True  # another worker's slot may free: look again then
                    asyncio.get_running_loop().call_later(RECHECK_SECONDS, self._recheck)
                return
            client, granted = min(eligible, key=lambda waiter: self._virtual_time(waiter[0]))
            self._waiting.remove((client, granted))
            self._free_slots -= 1
            self._computing[client] += 1
            if self._board is not None:
                self._board.note(client, computing=1)
            self._clock = self._virtual_time(client)
            self._used[client] = self._clock + self._cost.get(client, 0.0)
            granted.set_result(None)
