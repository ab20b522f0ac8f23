"""Fair shares of admission (service.api.http.admission) and who a client is (service.api.http.clients)."""

from __future__ import annotations

import asyncio
import os
import time
from contextlib import AsyncExitStack
from pathlib import Path

import pytest

from service.api.http.admission import Admission, Overloaded, OverShare
from service.api.http.clients import Client, ClientKeys
from service.infra.client_board import BOARD_VARIABLE, ClientBoard, client_board


def test_a_client_alone_may_take_every_place() -> None:
    async def scenario() -> None:
        admission = Admission(2, 2, 1.0, 1000, client_share=0.5)
        async with AsyncExitStack() as held:
            for _ in range(4):
                await held.enter_async_context(admission.admitted(client="a"))
            with pytest.raises(Overloaded):
                admission.refuse_if_full(client="a")

    asyncio.run(scenario())


def test_beside_another_client_one_holds_its_share_and_gets_429() -> None:
    async def scenario() -> None:
        admission = Admission(2, 6, 1.0, 1000, client_share=0.5)
        admission.refuse_if_full(client="polite")  # another client asked: shares apply
        async with AsyncExitStack() as held:
            for _ in range(4):
                await held.enter_async_context(admission.admitted(client="flood"))
            with pytest.raises(OverShare) as refused:
                admission.refuse_if_full(client="flood")
            assert refused.value.status == 429 and refused.value.headers == {"Retry-After": "1"}
            assert "holds 4 of the 4 predict places" in refused.value.detail
            assert "CKS_CLIENT_SHARE 0.5 of 8" in refused.value.detail
            async with admission.admitted(client="polite"):  # the other client keeps its places
                pass
            with pytest.raises(OverShare, match="this batch needs 5 places"):
                admission.refuse_if_full(5, client="polite")

    asyncio.run(scenario())


def test_beside_others_a_client_with_several_requests_computes_in_the_background() -> None:
    async def background(admission: Admission, client: str, places: int) -> bool:
        async with AsyncExitStack() as held:
            for _ in range(places):
                await held.enter_async_context(admission.admitted(client=client))
            async with admission.slot(client) as lowered:
                return lowered

    async def scenario() -> None:
        admission = Admission(4, 8, 1.0, 1000, client_share=0.5)
        assert not await background(admission, "flood", 3)  # alone: every place, at full priority
        admission.refuse_if_full(client="polite")  # another client asked: shares apply
        assert await background(admission, "flood", 3)
        assert await background(admission, "flood", 2)
        assert not await background(admission, "flood", 1)  # one at a time, as the polite client
        assert not await background(admission, "polite", 1)

    asyncio.run(scenario())


def test_a_free_slot_goes_to_the_client_computing_least() -> None:
    async def scenario() -> None:
        admission = Admission(2, 6, 5.0, 1000, client_share=0.5)
        for client in ("polite", "flood"):  # both asked: shares apply
            admission.refuse_if_full(client=client)
        order: list[str] = []
        release = asyncio.Event()

        async def compute(client: str) -> None:
            async with admission.slot(client):
                order.append(client)
                await release.wait()

        flood = [asyncio.create_task(compute("flood")) for _ in range(3)]
        await asyncio.sleep(0)
        assert order == ["flood"]  # one slot of two: its share while another client is active
        polite = asyncio.create_task(compute("polite"))
        await asyncio.sleep(0)
        assert order == ["flood", "polite"]  # the free slot, though the flood asked first
        release.set()
        await asyncio.gather(*flood, polite)
        assert order == ["flood", "polite", "flood", "flood"]

    asyncio.run(scenario())


def test_a_slot_wait_ends_at_the_queue_timeout() -> None:
    async def scenario() -> None:
        admission = Admission(1, 1, 0.05, 1000)
        async with admission.slot("a"):
            with pytest.raises(Overloaded, match="within 0.05 s"):
                async with admission.slot("b"):
                    pass
        async with admission.slot("b"):  # the timed-out wait left nothing behind
            pass

    asyncio.run(scenario())


def test_a_client_is_its_operator_then_a_trusted_header_then_its_address() -> None:
    keys = ClientKeys({"token-of-ann-0123456789": "ann"}, "X-Forwarded-For", ["10.0.0.0/8"])
    ann = keys.of("1.2.3.4", {"authorization": "Bearer token-of-ann-0123456789"})
    assert ann == Client("operator ann", "operator ann")  # a network of its own
    assert keys.of("1.2.3.4", {"authorization": "Bearer not-a-token"}).name == "1.2.3.4"
    # The header only from a trusted proxy; its last entry that is not a trusted proxy.
    assert keys.of("1.2.3.4", {"x-forwarded-for": "5.6.7.8"}).name == "1.2.3.4"
    assert keys.of("10.1.1.1", {"x-forwarded-for": "6.6.6.6, 5.6.7.8, 10.2.2.2"}).name == "5.6.7.8"
    assert keys.of("10.1.1.1", {"x-forwarded-for": " , "}).name == "10.1.1.1"
    assert keys.of(None, {}) == Client("unknown", "unknown")


def test_an_address_is_a_client_of_its_network() -> None:
    keys = ClientKeys({})  # the defaults: each address a client, of its /24 or /64
    assert keys.of("127.0.1.17", {}) == Client("127.0.1.17", "127.0.1.0/24")
    assert keys.of("2001:db8:1:2::5", {}) == Client("2001:db8:1:2::5", "2001:db8:1:2::/64")
    assert keys.of("not an address", {}) == Client("not an address", "not an address")
    per_network = ClientKeys({}, prefixes=(24, 64))  # a network as one client
    assert per_network.of("127.0.1.17", {}) == per_network.of("127.0.1.200", {})
    assert per_network.of("127.0.1.17", {}) == Client("127.0.1.0/24", "127.0.1.0/24")
    assert per_network.of("2001:db8:1:2::5", {}).name == "2001:db8:1:2::/64"
    proxied = ClientKeys({}, "X-Forwarded-For", ["10.0.0.1"], prefixes=(16, 128), network_prefixes=(24, 48))
    assert proxied.of("10.0.0.1", {"x-forwarded-for": "192.168.7.9"}) == Client(
        "192.168.0.0/16", "192.168.0.0/16"
    )
    assert ClientKeys({}, network_prefixes=(32, 128)).of("127.0.1.17", {}).network == "127.0.1.17"


def test_a_request_over_its_share_waits_for_its_own_place_then_gets_429_at_the_timeout() -> None:
    async def scenario() -> None:
        admission = Admission(1, 3, 0.2, 1000, client_share=0.5)  # 4 places, 2 per client
        await admission.wait_for_place(client="polite")  # another client asked: shares apply
        async with AsyncExitStack() as held:
            first = await held.enter_async_context(_Held(admission, "flood"))
            await held.enter_async_context(_Held(admission, "flood"))
            waiting = asyncio.create_task(admission.wait_for_place(client="flood"))
            await asyncio.sleep(0.05)
            assert not waiting.done()  # no 429 at once: it waits, holding nothing
            await admission.wait_for_place(client="polite")  # the other client does not wait
            await first.give_back()
            await asyncio.wait_for(waiting, 0.05)  # the flood's own place, handed over
            started = asyncio.get_running_loop().time()
            async with admission.admitted(client="flood"):  # the waiter takes it
                with pytest.raises(OverShare, match="holds 2 of the 2 predict places"):
                    await admission.wait_for_place(client="flood")
            assert asyncio.get_running_loop().time() - started >= 0.2  # 429 after the queue timeout

    asyncio.run(scenario())


def test_a_place_handed_over_as_another_wait_ends_leaves_the_waits_in_order() -> None:
    async def scenario() -> None:
        admission = Admission(1, 1, 0.1, 1000, client_share=0.5)  # 2 places, 1 per client
        await admission.wait_for_place(client="polite")
        async with AsyncExitStack() as held:
            place = await held.enter_async_context(_Held(admission, "flood"))
            handed, late = (asyncio.create_task(admission.wait_for_place(client="flood")) for _ in "ab")
            await asyncio.sleep(0.05)
            await place.give_back()  # to the first; the second's wait ends at the timeout
            await handed
            async with admission.admitted(client="flood"):  # the first takes its place
                with pytest.raises(OverShare):
                    await late
                again = asyncio.create_task(admission.wait_for_place(client="flood"))
                await asyncio.sleep(0.01)
            await asyncio.wait_for(again, 0.05)  # a new wait is handed the next place

    asyncio.run(scenario())


def test_a_free_slot_goes_to_the_client_that_used_least_a_new_one_first() -> None:
    async def scenario() -> None:
        admission = Admission(1, 8, 5.0, 1000)
        order: list[str] = []

        async def compute(client: str, seconds: float) -> None:
            async with admission.slot(client):
                order.append(client)
                await asyncio.sleep(seconds)

        await compute("heavy", 0.1)
        await compute("light", 0.01)
        blocker = asyncio.create_task(compute("blocker", 0.05))
        await asyncio.sleep(0)
        waiting = [asyncio.create_task(compute(client, 0)) for client in ("heavy", "light", "new")]
        await asyncio.gather(blocker, *waiting)
        # Asked in the order heavy, light, new: served by compute used; the new client starts at
        # the virtual time now, ahead of every client that used more since.
        assert order[3:] == ["new", "light", "heavy"]

    asyncio.run(scenario())


_POLITE = Client("10.0.0.7", "10.0.0.0/24")
_SPREAD = [Client(f"10.0.1.{n}", "10.0.1.0/24") for n in range(1, 101)]  # a flood over one network


def test_a_flood_spread_over_one_network_holds_one_networks_share_of_the_places() -> None:
    async def scenario() -> None:
        admission = Admission(2, 6, 0.05, 1000, client_share=0.5)  # 8 places, 4 per client or network
        admission.refuse_if_full(client=_POLITE)
        async with AsyncExitStack() as held:
            for client in _SPREAD[:4]:  # each address within its own share ...
                await held.enter_async_context(admission.admitted(client=client))
            with pytest.raises(OverShare) as refused:  # ... the network at its own
                await admission.wait_for_place(client=_SPREAD[4])
            assert "network (10.0.1.0/24: CKS_CLIENT_NETWORK_IPV4_PREFIX" in refused.value.detail
            assert "already holds 4 of the 4 predict places one network may hold" in refused.value.detail
            for _ in range(4):  # the other network's client keeps its places
                await held.enter_async_context(admission.admitted(client=_POLITE))

    asyncio.run(scenario())


def test_within_one_network_the_shares_are_the_clients() -> None:
    async def scenario() -> None:
        admission = Admission(2, 6, 0.05, 1000, client_share=0.5)
        neighbours = Client("10.0.1.200", "10.0.1.0/24"), _SPREAD[0]
        admission.refuse_if_full(client=neighbours[0])  # two clients of one network: no network share
        async with AsyncExitStack() as held:
            for _ in range(4):
                await held.enter_async_context(admission.admitted(client=neighbours[1]))
            with pytest.raises(OverShare, match=r"this client \(10.0.1.1\) already holds 4 of the 4"):
                admission.refuse_if_full(client=neighbours[1])
            for _ in range(4):
                await held.enter_async_context(admission.admitted(client=neighbours[0]))

    asyncio.run(scenario())


def test_a_place_of_a_network_goes_to_its_oldest_waiting_request_within_its_shares() -> None:
    async def scenario() -> None:
        admission = Admission(1, 3, 1.0, 1000, client_share=0.5)  # 2 places per client or network
        admission.refuse_if_full(client=_POLITE)
        async with AsyncExitStack() as held:
            first = await held.enter_async_context(_Held(admission, _SPREAD[0]))
            await held.enter_async_context(_Held(admission, _SPREAD[1]))
            waiting = asyncio.create_task(admission.wait_for_place(client=_SPREAD[2]))
            await asyncio.sleep(0.01)
            assert not waiting.done()  # its network holds its share
            await first.give_back()  # another address's place of the same network
            await asyncio.wait_for(waiting, 0.05)

    asyncio.run(scenario())


def test_a_free_slot_goes_to_the_network_computing_least_then_to_its_client() -> None:
    async def scenario() -> None:
        admission = Admission(2, 30, 5.0, 1000, client_share=0.5)  # 1 slot per client or network
        order: list[Client] = []
        release = asyncio.Event()

        async def compute(client: Client) -> bool:
            async with admission.slot(client) as background:
                order.append(client)
                await release.wait()
                return background

        admission.refuse_if_full(client=_POLITE)
        flood = []
        for client in _SPREAD[:10]:
            async with AsyncExitStack() as held:  # each address holds one place; its network ten
                await held.enter_async_context(admission.admitted(client=client))
            flood.append(asyncio.create_task(compute(client)))
        await asyncio.sleep(0)
        assert order == [_SPREAD[0]]  # the network's one slot of two, though each address holds one
        polite = asyncio.create_task(compute(_POLITE))
        await asyncio.sleep(0)
        assert order == [_SPREAD[0], _POLITE]  # the free slot, though ten asked first
        release.set()
        await asyncio.gather(*flood, polite)
        assert order[2:] == _SPREAD[1:10]  # one at a time, oldest first among equals

    asyncio.run(scenario())


def test_beside_another_network_a_network_with_several_places_computes_in_the_background() -> None:
    async def background(admission: Admission, holders: list[Client]) -> bool:
        async with AsyncExitStack() as held:
            for client in holders:
                await held.enter_async_context(admission.admitted(client=client))
            async with admission.slot(holders[0]) as lowered:
                return lowered

    async def scenario() -> None:
        admission = Admission(4, 8, 1.0, 1000, client_share=0.5)
        assert not await background(admission, _SPREAD[:3])  # its clients alone: full priority
        admission.refuse_if_full(client=_POLITE)
        assert await background(admission, _SPREAD[:3])  # one place each, three for the network
        assert not await background(admission, _SPREAD[:1])
        assert not await background(admission, [_POLITE])

    asyncio.run(scenario())


def test_the_board_tells_a_worker_of_the_clients_of_another(tmp_path: Path) -> None:
    with client_board(2, tmp_path) as path:
        assert path is not None and os.environ[BOARD_VARIABLE] == str(path)
        mine, other = ClientBoard.joined(), ClientBoard.joined()  # two workers' rows
        assert mine is not None and other is not None
        other.note("polite")
        admission = Admission(1, 3, 0.05, 1000, client_share=0.5, board=mine)
        for _ in range(2):
            admission.refuse_if_full(client="flood")  # the only client this worker saw ...
        assert mine.several_since(30) and not ClientBoard.joined().several_since(0)  # type: ignore[union-attr]

        async def scenario() -> None:
            async with admission.admitted(client="flood"), admission.admitted(client="flood"):
                with pytest.raises(OverShare):  # ... held to its share: another worker serves polite
                    await admission.wait_for_place(client="flood")

        asyncio.run(scenario())
    assert not path.exists() and BOARD_VARIABLE not in os.environ


def test_a_compute_share_holds_across_the_workers_of_a_board(tmp_path: Path) -> None:
    async def scenario(mine: ClientBoard, other: ClientBoard) -> None:
        admission = Admission(2, 4, 5.0, 1000, client_share=0.5, board=mine)  # 1 of 2 slots per client
        other.note("polite")
        other.note("flood", computing=1)  # another worker computes the flood's one slot
        admission.refuse_if_full(client="flood")
        waiting = asyncio.create_task(_compute(admission, "flood"))
        await asyncio.sleep(0.1)
        assert not waiting.done()  # a slot is free here, but not the flood's share of the group's
        other.note("flood", computing=-1)
        await asyncio.wait_for(waiting, 1.0)  # seen within RECHECK_SECONDS

    with client_board(2, tmp_path):
        mine, other = ClientBoard.joined(), ClientBoard.joined()
        assert mine is not None and other is not None
        asyncio.run(scenario(mine, other))


async def _compute(admission: Admission, client: Client | str) -> None:
    async with admission.slot(client):
        pass


def test_a_networks_compute_share_holds_across_the_workers_of_a_board(tmp_path: Path) -> None:
    async def scenario(mine: ClientBoard, other: ClientBoard) -> None:
        admission = Admission(2, 4, 5.0, 1000, client_share=0.5, board=mine)
        other.note(_POLITE.name, network=_POLITE.network)
        other.note(_SPREAD[0].name, computing=1, network=_SPREAD[0].network)  # its network's one slot
        admission.refuse_if_full(client=_SPREAD[1])  # this worker sees one client of one network
        assert mine.several_networks_since(30)
        waiting = asyncio.create_task(_compute(admission, _SPREAD[1]))
        await asyncio.sleep(0.1)
        assert not waiting.done()  # another address, but the network's share of the group's slots
        other.note(_SPREAD[0].name, computing=-1, network=_SPREAD[0].network)
        await asyncio.wait_for(waiting, 1.0)

    with client_board(2, tmp_path):
        mine, other = ClientBoard.joined(), ClientBoard.joined()
        assert mine is not None and other is not None
        asyncio.run(scenario(mine, other))
    with client_board(2, tmp_path):
        board = ClientBoard.joined()
        assert board is not None
        for client in _SPREAD[:3]:
            board.note(client.name, network=client.network)
        assert board.several_since(30) and not board.several_networks_since(30)


def test_a_flood_of_one_network_leaves_a_lone_client_of_another_on_the_board(tmp_path: Path) -> None:
    with client_board(2, tmp_path):
        mine, other = ClientBoard.joined(), ClientBoard.joined()
        assert mine is not None and other is not None
        mine.note(_POLITE.name, network=_POLITE.network)
        for client in _SPREAD[:40]:  # far more clients than a row holds, all of one network
            time.sleep(0.001)
            mine.note(client.name, network=client.network)
        assert other.several_networks_since(30)  # the other worker still sees two networks


def test_a_board_left_under_this_pid_by_a_killed_predecessor_is_replaced(tmp_path: Path) -> None:
    stale = tmp_path / f"cks-clients-{os.getpid()}"  # what a SIGKILLed pid 1 leaves in /dev/shm
    stale.write_bytes(b"a predecessor's rows")
    with client_board(2, tmp_path) as path:
        assert path == stale and path.stat().st_size > len(b"a predecessor's rows")
        board = ClientBoard.joined()
        assert board is not None and not board.several_since(0)
    assert not stale.exists()


def test_without_a_board_each_worker_keeps_its_own_shares(tmp_path: Path) -> None:
    with client_board(1, tmp_path) as one_worker:
        assert one_worker is None and ClientBoard.joined() is None
    with client_board(2, tmp_path / "missing") as unavailable:  # as a /dev/shm that cannot be written
        assert unavailable is None and ClientBoard.joined() is None
    assert ClientBoard.joined(str(tmp_path / "missing")) is None


class _Held:
    """A place of ``client`` held until ``give_back``."""

    def __init__(self, admission: Admission, client: Client | str) -> None:
        self._place = admission.admitted(client=client)

    async def __aenter__(self) -> _Held:
        await self._place.__aenter__()
        return self

    async def __aexit__(self, *exc: object) -> None:
        await self.give_back()

    async def give_back(self) -> None:
        if self._place is not None:
            place, self._place = self._place, None
            await place.__aexit__(None, None, None)
