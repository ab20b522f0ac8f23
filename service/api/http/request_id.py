"""The request id: taken from ``X-Request-ID`` or generated, logged on every line, sent back."""

from __future__ import annotations

import re
import uuid

from starlette.datastructures import Headers, MutableHeaders
from starlette.types import Message, Receive, Scope, Send

from service.api.http.http_middleware import HttpMiddleware
from service.infra.logs import begin_request

HEADER = "X-Request-ID"
MAX_LENGTH = 128
# Visible ASCII only: an id goes into log lines verbatim, so no spaces, control characters
# (a forged line break) or anything a terminal would interpret.
_VALID = re.compile(rf"[\x21-\x7e]{{1,{MAX_LENGTH}}}")


def request_id(presented: str | None) -> str:
    """The caller's id if it is 1 to 128 visible ASCII characters, else a new one (32 hex digits)."""
    return presented if presented is not None and _VALID.fullmatch(presented) else uuid.uuid4().hex


class RequestIdMiddleware(HttpMiddleware):
    """Makes the request's id the id of its log lines and returns it in ``X-Request-ID``. The context
    variable is not reset: each request's task ends it, and lines logged after the app returned (the
    500 handler, outside every middleware, and uvicorn's report of the exception) still carry the id."""

    async def handle(self, scope: Scope, receive: Receive, send: Send) -> None:
        context = begin_request(request_id(Headers(scope=scope).get(HEADER)))

        async def send_with_id(message: Message) -> None:
            if message["type"] == "http.response.start":
                MutableHeaders(scope=message)[HEADER] = context.request_id
            await send(message)

        await self.app(scope, receive, send_with_id)
