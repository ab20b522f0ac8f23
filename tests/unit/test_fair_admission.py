"""Fair shares of admission (service.api.http.admission) and who a client is (service.api.http.clients)."""

from __future__ import annotations

import asyncio
from contextlib import AsyncExitStack

import pytest

from service.api.http.admission import Admission, Overloaded, OverShare
from service.api.http.clients import ClientKeys


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
