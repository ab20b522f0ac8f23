"""Fair shares of admission (service.api.http.admission) and who a client is (service.api.http.clients)."""

from __future__ import annotations

import asyncio
import os
from contextlib import AsyncExitStack
from pathlib import Path

import pytest

from service.api.http.admission import Admission, Overloaded, OverShare
from service.api.http.clients import ClientKeys
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
    assert keys.of("1.2.3.4", {"authorization": "Bearer token-of-ann-0123456789"}) == "operator ann"
    assert keys.of("1.2.3.4", {"authorization": "Bearer not-a-token"}) == "1.2.3.4"
    # The header only from a trusted proxy; its last entry that is not a trusted proxy.
    assert keys.of("1.2.3.4", {"x-forwarded-for": "5.6.7.8"}) == "1.2.3.4"
    assert keys.of("10.1.1.1", {"x-forwarded-for": "6.6.6.6, 5.6.7.8, 10.2.2.2"}) == "5.6.7.8"
    assert keys.of("10.1.1.1", {"x-forwarded-for": " , "}) == "10.1.1.1"
    assert keys.of(None, {}) == "unknown"


def test_an_address_stands_for_its_network_of_the_configured_prefix() -> None:
    per_network = ClientKeys({}, prefixes=(24, 64))
    assert per_network.of("127.0.1.17", {}) == per_network.of("127.0.1.200", {}) == "127.0.1.0/24"
    assert per_network.of("127.0.0.1", {}) == "127.0.0.0/24"
    assert per_network.of("2001:db8:1:2::5", {}) == "2001:db8:1:2::/64"
    assert ClientKeys({}).of("127.0.1.17", {}) == "127.0.1.17"  # the default: each address
    proxied = ClientKeys({}, "X-Forwarded-For", ["10.0.0.1"], prefixes=(16, 128))
    assert proxied.of("10.0.0.1", {"x-forwarded-for": "192.168.7.9"}) == "192.168.0.0/16"


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


async def _compute(admission: Admission, client: str) -> None:
    async with admission.slot(client):
        pass


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

    def __init__(self, admission: Admission, client: str) -> None:
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
