"""Admission (service.api.http.admission): places, compute slots and each caller's share of them."""

from __future__ import annotations

import asyncio
from contextlib import AsyncExitStack

import pytest

from service.api.http.admission import Admission, Overloaded
from service.errors import TooManyRequests


def test_a_caller_alone_may_take_every_place_then_gets_503() -> None:
    async def scenario() -> None:
        admission = Admission(2, 2, share=0.5)
        async with AsyncExitStack() as held:
            for _ in range(4):
                await admission.wait_for_place("a")
                await held.enter_async_context(admission.admitted("a"))
            with pytest.raises(Overloaded) as refused:
                admission.refuse_if_full("a")
            assert refused.value.status == 503 and refused.value.headers == {"Retry-After": "1"}
            assert "at capacity (2 predict requests computing, 2 waiting" in refused.value.detail

    asyncio.run(scenario())


def test_beside_another_caller_one_holds_its_share_and_gets_429() -> None:
    async def scenario() -> None:
        admission = Admission(2, 6, share=0.5)
        await admission.wait_for_place("polite")  # another caller asked: shares apply
        async with AsyncExitStack() as held:
            for _ in range(4):
                await held.enter_async_context(admission.admitted("flood"))
            with pytest.raises(TooManyRequests) as refused:
                admission.refuse_if_full("flood")
            assert refused.value.status == 429 and refused.value.headers == {"Retry-After": "1"}
            assert "(flood) already holds 4 of the 4 predict places" in refused.value.detail
            assert "CKS_CLIENT_SHARE 0.5 of 8" in refused.value.detail
            async with admission.admitted("polite"):  # the other caller keeps its places
                pass
            with pytest.raises(TooManyRequests, match="this batch needs 5 places"):
                admission.refuse_if_full("polite", 5)

    asyncio.run(scenario())


def test_a_request_over_its_share_waits_for_its_own_place_then_gets_429_at_the_timeout() -> None:
    async def scenario() -> None:
        admission = Admission(1, 3, share=0.5, timeout=0.2)  # 4 places, 2 per caller
        await admission.wait_for_place("polite")
        async with AsyncExitStack() as held:
            first = AsyncExitStack()
            await first.enter_async_context(admission.admitted("flood"))
            await held.enter_async_context(admission.admitted("flood"))
            waiting = asyncio.create_task(admission.wait_for_place("flood"))
            await asyncio.sleep(0.05)
            assert not waiting.done()  # no 429 at once: it waits, holding nothing
            await admission.wait_for_place("polite")  # the other caller does not wait
            await first.aclose()  # one of the flood's places given back
            await asyncio.wait_for(waiting, 0.05)  # ... goes to its waiting request
            started = asyncio.get_running_loop().time()
            async with admission.admitted("flood"):
                with pytest.raises(TooManyRequests, match="holds 2 of the 2 predict places"):
                    await admission.wait_for_place("flood")
            assert asyncio.get_running_loop().time() - started >= 0.2  # 429 after the timeout

    asyncio.run(scenario())


def test_a_callers_share_of_the_compute_threads_leaves_a_slot_for_another() -> None:
    async def scenario() -> None:
        admission = Admission(4, 4, share=0.5, threads=2)  # one thread per caller while shared
        await admission.wait_for_place("polite")
        order: list[str] = []

        async def compute(caller: str, release: asyncio.Event) -> None:
            async with admission.slot(caller):
                order.append(caller)
                await release.wait()

        release = asyncio.Event()
        floods = [asyncio.create_task(compute("flood", release)) for _ in range(3)]
        await asyncio.sleep(0.01)
        assert order == ["flood"]  # its one thread; the other requests wait beside free slots
        polite = asyncio.create_task(compute("polite", release))
        await asyncio.sleep(0.01)
        assert order == ["flood", "polite"]  # a slot at once, ahead of the flood's waiting ones
        release.set()
        await asyncio.gather(*floods, polite)
        assert order == ["flood", "polite", "flood", "flood"]

    asyncio.run(scenario())


def test_a_caller_alone_computes_on_every_slot() -> None:
    async def scenario() -> None:
        admission = Admission(3, 0, share=0.5, threads=2)
        await admission.wait_for_place("alone")
        async with AsyncExitStack() as held:
            for _ in range(3):
                await asyncio.wait_for(held.enter_async_context(admission.slot("alone")), 0.05)

    asyncio.run(scenario())


def test_a_slot_wait_ends_at_the_timeout_and_leaves_nothing_behind() -> None:
    async def scenario() -> None:
        admission = Admission(1, 1, timeout=0.05)
        async with admission.slot("a"):
            with pytest.raises(Overloaded, match="within 0.05 s"):
                async with admission.slot("b"):
                    pass
        async with admission.slot("b"):
            pass

    asyncio.run(scenario())


def test_a_cancelled_slot_wait_leaves_nothing_behind() -> None:
    async def scenario() -> None:
        admission = Admission(1, 1)
        async with admission.slot("a"):
            waiting = asyncio.create_task(admission.slot("b").__aenter__())
            await asyncio.sleep(0.01)
            waiting.cancel()
            with pytest.raises(asyncio.CancelledError):
                await waiting
        async with admission.slot("b"):  # the slot is free, and nobody is left waiting for it
            pass

    asyncio.run(scenario())


def test_a_slot_freed_as_every_request_is_cancelled_goes_to_nobody() -> None:
    """A shutdown cancels every request at once: the computing one's slot, given back, must skip
    the waiters whose requests were cancelled too (their futures are done), never fail on them."""

    async def scenario() -> None:
        admission = Admission(1, 3)
        release = asyncio.Event()

        async def compute() -> None:
            async with admission.slot("a"):
                await release.wait()

        tasks = [asyncio.create_task(compute()) for _ in range(3)]
        await asyncio.sleep(0.01)
        for task in tasks:
            task.cancel()
        results = await asyncio.gather(*tasks, return_exceptions=True)
        assert all(isinstance(result, asyncio.CancelledError) for result in results), results
        async with admission.slot("b"):  # nothing left behind
            pass

    asyncio.run(scenario())
