"""Request headers bounded in count and size (431): the proxy in front bounds them before they are
read (deploy/haproxy), and a service reached without one still refuses a request that carries a
megabyte of headers or thousands of them."""

from __future__ import annotations

from starlette.requests import Request
from starlette.types import Receive, Scope, Send

from service.api.http.http_middleware import HttpMiddleware
from service.api.http.problems import problem

MAX_HEADERS = 100
MAX_HEADER_BYTES = 16 * 1024  # names and values together, as HAProxy's and nginx's default buffers


class HeaderLimits(HttpMiddleware):
    """Answers 431 to a request with more than ``MAX_HEADERS`` headers or ``MAX_HEADER_BYTES`` of them."""

    async def handle(self, scope: Scope, receive: Receive, send: Send) -> None:
        headers = scope["headers"]
        size = sum(len(name) + len(value) for name, value in headers)
        if len(headers) <= MAX_HEADERS and size <= MAX_HEADER_BYTES:
            await self.app(scope, receive, send)
            return
        detail = (
            f"the request has {len(headers)} headers of {size} bytes; at most {MAX_HEADERS} headers of"
            f" {MAX_HEADER_BYTES} bytes together are read: send fewer or shorter headers"
        )
        answer = problem(431, "Request header fields too large", detail, Request(scope))
        await answer(scope, receive, send)
