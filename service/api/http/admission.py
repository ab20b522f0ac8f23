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

Fair shares, at two levels: between networks, then between the clients of one
(``service.api.http.clients``: a client is an address by default, its network a /24 or a /64).
While more than one client has asked in the last ``ACTIVE_SECONDS``, one client may hold at most
``max(1, places x share)`` of the places (``client_share``, CKS_CLIENT_SHARE) and compute on at
most ``max(1, threads x share)`` slots (threads: the slots that really run at once, the fewer of
the slots, CKS_CPU_WORKERS and the usable cores); while clients of more than one network have
asked, so may one network, all its clients together. A request beyond its client's (or its
network's) places waits, before its body is received and holding nothing, for a place to be
given back, at most the queue timeout; then it is refused with 429 and ``Retry-After`` (a flood
that ignores Retry-After would otherwise come back at once, and the event loop would spend
itself refusing). A free slot goes to a waiting request of the network that has used the least
compute, and within it of the client that has (start-time fair queueing: each one's virtual
time advances by the seconds its requests hold a slot, and one that was idle starts at the
virtual time now, so it goes ahead of every one with work waiting; the oldest first among
equals). So one client's flood waits beyond its share, behind a client that asks little, and a
flood spread over the addresses of one network holds one network's share; a client alone may
use every place. With several workers, a board in shared memory
(``service.infra.client_board``) tells each which clients (and networks) the others serve and
on how many slots, so that whether shares apply and the slots hold for the process group.
"""

from __future__ import annotations

import asyncio
import time
from collections import Counter, deque
from collections.abc import AsyncIterator, Callable, Iterator
from contextlib import asynccontextmanager, contextmanager

from service.api.http.clients import Client
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


class FairClock:
    """Start-time fair queueing's virtual time, per key (a client or a network): a key's advances
    by the seconds its requests hold a slot, and a key that was idle starts at the virtual time now."""

    def __init__(self) -> None:
        self._now = 0.0  # the start of the last slot granted
        self._used: dict[str, float] = {}  # key -> its virtual time (compute seconds charged)
        self._cost: dict[str, float] = {}  # key -> seconds its last slot was held (the next's guess)

    def of(self, key: str) -> float:
        return max(self._used.get(key, 0.0), self._now)

    def start(self, key: str) -> None:
        """A slot granted to ``key`` now: charged its last slot's seconds until ``charge`` corrects them."""
        self._now = self.of(key)
        self._used[key] = self._now + self._cost.get(key, 0.0)

    def charge(self, key: str, seconds: float) -> None:
        """Correct the guess charged when ``key``'s slot was granted by what it really held."""
        if key in self._used:
            self._used[key] += seconds - self._cost.get(key, 0.0)
        self._cost[key] = seconds

    def forget(self, key: str) -> None:
        self._used.pop(key, None)
        self._cost.pop(key, None)


class Admission:
    """Counts received bytes and admitted requests, and hands out the compute slots, per client
    and per network. Used from the event loop only; a client given as a string is a network of
    its own."""

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
        self._held: Counter[str] = Counter()  # places per client, and per network
        self._network_held: Counter[str] = Counter()
        self._computing: Counter[str] = Counter()  # slots per client, and per network
        self._network_computing: Counter[str] = Counter()
        self._free_slots = max_concurrent
        self._waiting: list[tuple[Client, asyncio.Future[None]]] = []  # oldest first
        self._asked: dict[str, float] = {}  # client -> when it last asked, least recent first
        self._networks: Counter[str] = Counter()  # network -> its clients in ``_asked``
        self._network_of: dict[str, str] = {}  # client in ``_asked`` -> its network
        self._board = board  # the clients of the other workers (CKS_WORKERS), where there is one
        self._rechecking = False  # a look at the board's slots is due
        self._clients_clock, self._networks_clock = FairClock(), FairClock()
        self._place_waiters: dict[str, deque[tuple[Client, asyncio.Future[None]]]] = {}  # per network

    @property
    def capacity(self) -> int:
        """Places in all: computing plus waiting."""
        return self._max_concurrent + self._max_queued

    async def wait_for_place(self, places: int = 1, client: Client | str = "") -> None:
        """Before a body is received: while ``client`` (or its network) holds its share of the
        places, wait (holding nothing) until a place of its network is given back, its requests
        in order, at most the queue timeout; then as ``refuse_if_full``. A flood thus waits
        instead of coming back at once."""
        client = _as_client(client)
        self._note(client)
        line = self._place_waiters.get(client.network, ())
        waits = self._over_share(client, places) or any(waiter == client for waiter, _ in line)
        if waits and places <= self._client_places:  # a batch that can never fit is refused at once
            await self._queue_for_place(client)
        self.refuse_if_full(places, client)

    async def _queue_for_place(self, client: Client) -> None:
        freed = asyncio.get_running_loop().create_future()
        line = self._place_waiters.setdefault(client.network, deque())
        entry = (client, freed)
        line.append(entry)
        try:
            async with asyncio.timeout(self._timeout):
                await freed
        except TimeoutError:
            pass  # refused below with 429
        finally:
            if entry in line:
                line.remove(entry)
            if not line and self._place_waiters.get(client.network) is line:
                del self._place_waiters[client.network]

    def _over_share(self, client: Client, places: int) -> str:
        """What ``client`` would hold beyond its share with ``places`` more: "" (nothing), its
        client's or its network's places."""
        if self._client_places >= self.capacity:
            return ""
        if self._held[client.name] + places > self._client_places and self._shared():
            return "client"
        if self._network_held[client.network] + places > self._client_places and self._networks_shared():
            return "network"
        return ""

    def refuse_if_full(self, places: int = 1, client: Client | str = "") -> None:
        """429 when ``client`` (or its network) would hold more than its share of the places while
        others are active (CKS_CLIENT_SHARE); 503 unless ``places`` places (one per image) are free
        (CKS_MAX_QUEUED_REQUESTS)."""
        client = _as_client(client)
        self._note(client)
        needs = f"; this batch needs {places} places, one per image" if places > 1 else ""
        if over := self._over_share(client, places):
            PREDICT_REJECTED.labels("client_share").inc()
            raise OverShare(
                f"{self._holding(client, over)} (CKS_CLIENT_SHARE {self._share:g} of {self.capacity}){needs}:"
                f" retry after {RETRY_AFTER_SECONDS} s"
            )
        if self._admitted + places > self.capacity:
            PREDICT_REJECTED.labels("queue_full").inc()
            raise Overloaded(
                f"the service is at capacity ({self._max_concurrent} predict requests computing, "
                f"{self._max_queued} waiting; CKS_MAX_CONCURRENT_INFERENCES, CKS_MAX_QUEUED_REQUESTS)"
                f"{needs}: retry after {RETRY_AFTER_SECONDS} s"
            )

    def _holding(self, client: Client, over: str) -> str:
        if over == "client":
            return (
                f"this client ({client.name}) already holds {self._held[client.name]} of the"
                f" {self._client_places} predict places one client may hold while others are served"
            )
        return (
            f"this client's network ({client.network}: CKS_CLIENT_NETWORK_IPV4_PREFIX,"
            f" CKS_CLIENT_NETWORK_IPV6_PREFIX) already holds {self._network_held[client.network]} of the"
            f" {self._client_places} predict places one network may hold while other networks are served"
        )

    def _note(self, client: Client) -> None:
        """Remember that ``client`` asked now; forget the clients quiet for ACTIVE_SECONDS."""
        now = time.monotonic()
        if self._board is not None:
            self._board.note(client.name, network=client.network)
        if self._asked.pop(client.name, None) is None:
            self._networks[client.network] += 1
            self._network_of[client.name] = client.network
        self._asked[client.name] = now
        while now - self._asked[oldest := next(iter(self._asked))] > ACTIVE_SECONDS:
            del self._asked[oldest]
            self._clients_clock.forget(oldest)
            network = self._network_of.pop(oldest)
            self._networks[network] -= 1
            if not self._networks[network]:
                del self._networks[network]
                self._networks_clock.forget(network)

    def _shared(self) -> bool:
        """Whether more than one client is active in this worker or any other: shares apply only then."""
        board = self._board
        return len(self._asked) > 1 or (board is not None and board.several_since(ACTIVE_SECONDS))

    def _networks_shared(self) -> bool:
        """Whether clients of more than one network are active: networks' shares apply only then."""
        board = self._board
        return len(self._networks) > 1 or (board is not None and board.several_networks_since(ACTIVE_SECONDS))

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
    async def admitted(self, places: int = 1, client: Client | str = "") -> AsyncIterator[None]:
        """Take ``places`` places (computing or waiting for a slot; one per image), or fail fast."""
        client = _as_client(client)
        self.refuse_if_full(places, client)
        self._admitted += places
        _count(self._held, client.name, places)
        _count(self._network_held, client.network, places)
        PREDICT_IN_FLIGHT.inc(places)
        try:
            yield
        finally:
            self._admitted -= places
            _count(self._held, client.name, -places)
            _count(self._network_held, client.network, -places)
            PREDICT_IN_FLIGHT.dec(places)
            self._hand_over(client.network)

    def _hand_over(self, network: str) -> None:
        """A place a client of ``network`` gave back goes to the oldest request of the network
        waiting for one that is now within its shares."""
        for entry in list(self._place_waiters.get(network, ())):
            waiter, freed = entry
            if not freed.done() and not self._over_share(waiter, 1):  # not one whose wait just ended
                self._place_waiters[network].remove(entry)
                freed.set_result(None)
                return

    @asynccontextmanager
    async def slot(self, client: Client | str = "") -> AsyncIterator[bool]:
        """A compute slot, waited for at most the queue timeout (CKS_QUEUE_TIMEOUT_SECONDS); yields
        whether to compute at background priority (``service.infra.cpu_priority``): while others
        are served, a request of a client (or of a network, while other networks are) holding
        several places, so that the kernel gives a one-at-a-time client's request the cores first."""
        client = _as_client(client)
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
        background = (self._held[client.name] > 1 and self._shared()) or (
            self._network_held[client.network] > 1 and self._networks_shared()
        )
        PREDICT_COMPUTING.inc()
        started = time.monotonic()
        try:
            yield background
        finally:
            PREDICT_COMPUTING.dec()
            held = time.monotonic() - started
            self._clients_clock.charge(client.name, held)
            self._networks_clock.charge(client.network, held)
            self._give_back(client)

    async def _take_slot(self, client: Client) -> None:
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

    def _give_back(self, client: Client) -> None:
        _count(self._computing, client.name, -1)
        _count(self._network_computing, client.network, -1)
        if self._board is not None:
            self._board.note(client.name, computing=-1, network=client.network)
        self._free_slots += 1
        self._grant()

    def _recheck(self) -> None:
        self._rechecking = False
        self._grant()

    def _at_share(self, waiting: list[Client]) -> tuple[set[str], set[str]]:
        """The waiting clients (names) and networks that compute on their share of the slots,
        where that share applies, in every worker where there is a board: each looked up once per
        grant, not once per waiting request."""
        board = self._board
        clients = {c.name for c in waiting} if self._shared() else set()
        networks = {c.network for c in waiting} if self._networks_shared() else set()
        return (
            {
                name
                for name in clients
                if self._at_its_share(self._computing, name, board and board.computing)
            },
            {
                net
                for net in networks
                if self._at_its_share(self._network_computing, net, board and board.network_computing)
            },
        )

    def _at_its_share(self, here: Counter[str], key: str, anywhere: Callable[[str], int] | None) -> bool:
        """Whether ``key`` computes on its share of the slots here, or in all workers."""
        return max(here[key], anywhere(key) if anywhere else 0) >= self._client_slots

    def _grant(self) -> None:
        """Free slots to waiting requests: of the network that has used least (its virtual time),
        then of its client that has, oldest first; a client or network at its share of the slots
        waits while others are active."""
        self._waiting = [waiter for waiter in self._waiting if not waiter[1].done()]
        while self._free_slots:
            clients, networks = self._at_share([client for client, _ in self._waiting])
            eligible = [w for w in self._waiting if w[0].name not in clients and w[0].network not in networks]
            if not eligible:
                if self._waiting and self._board is not None and not self._rechecking:
                    self._rechecking = True  # another worker's slot may free: look again then
                    asyncio.get_running_loop().call_later(RECHECK_SECONDS, self._recheck)
                return
            client, granted = min(eligible, key=self._fair_order)
            self._waiting.remove((client, granted))
            self._free_slots -= 1
            _count(self._computing, client.name, 1)
            _count(self._network_computing, client.network, 1)
            if self._board is not None:
                self._board.note(client.name, computing=1, network=client.network)
            self._networks_clock.start(client.network)
            self._clients_clock.start(client.name)
            granted.set_result(None)

    def _fair_order(self, waiter: tuple[Client, asyncio.Future[None]]) -> tuple[float, float]:
        client = waiter[0]
        return self._networks_clock.of(client.network), self._clients_clock.of(client.name)


def _as_client(client: Client | str) -> Client:
    return Client(client, client) if isinstance(client, str) else client


def _count(counter: Counter[str], key: str, change: int) -> None:
    """Add ``change`` to ``key``'s count, dropping it at zero (counters of active keys stay small)."""
    counter[key] += change
    if not counter[key]:
        del counter[key]
