"""Requests cut at the end of a shutdown's grace period answer 503, never uvicorn's 500.

When SIGTERM's grace period (CKS_SHUTDOWN_GRACE_SECONDS) ends, uvicorn cancels the requests
still running: a predict computing, an upload still arriving, an admin call waiting on the
store. One whose response has not started answers 503 problem+json with ``Retry-After: 1`` and
``Connection: close``; what each had done is undone by its own cleanup (a partial upload is
removed; a store transaction not committed is rolled back).
"""

from __future__ import annotations

import asyncio

from starlette.requests import Request
from starlette.types import Message, Receive, Scope, Send

from service.api.http.http_middleware import HttpMiddleware
from service.api.http.problems import problem
from service.errors import Unavailable

CUT = Unavailable(
    "the service stopped before this request was done (CKS_SHUTDOWN_GRACE_SECONDS): send it again",
    headers={"Retry-After": "1", "Connection": "close"},
)


class AnswerCutRequests(HttpMiddleware):
    """Turns the cancellation of a request whose response has not started into CUT's 503."""

    async def handle(self, scope: Scope, receive: Receive, send: Send) -> None:
        started = False

        async def send_noting_start(message: Message) -> None:
            nonlocal started
            started = started or message["type"] == "http.response.start"
            await send(message)

        try:
            await self.app(scope, receive, send_noting_start)
        except asyncio.CancelledError:
            if started:
                raise
            answer = problem(CUT.status, CUT.title, CUT.detail, Request(scope), headers=CUT.headers)
            await answer(scope, receive, send)
