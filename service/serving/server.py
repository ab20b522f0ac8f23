"""The HTTP server: uvicorn serving ``service.serving.main:app``, configured from Settings.

What a public port needs beyond uvicorn's defaults:

- **Slow request heads.** uvicorn has no timeout on a request's line and headers: a client
  sending them a byte at a time held its connection for ever. ``HeadTimeoutProtocol``
  answers 408 and closes a connection whose head has not arrived within
  ``CKS_HEADER_READ_TIMEOUT_SECONDS`` of the connection opening (or of the first byte of
  a later request on a kept-alive connection).
- **Open connections.** At most ``CKS_MAX_CONNECTIONS`` per process are served (uvicorn's
  ``limit_concurrency``): a request on one more gets 503.
- **Slow bodies** are paced where they are read (``service.api.http.request_body``): predict bodies
  within ``CKS_REQUEST_READ_TIMEOUT_SECONDS``, uploads within
  ``CKS_UPLOAD_READ_TIMEOUT_SECONDS``, both at ``CKS_MIN_BODY_BYTES_PER_SECOND`` or faster.
- **SIGTERM.** uvicorn stops accepting connections, closes idle ones and gives in-flight
  requests up to ``CKS_SHUTDOWN_GRACE_SECONDS``; then the app's shutdown marks running
  calibration jobs interrupted without waiting for them (``ServiceState.close``), and the
  process exits 0.
"""

from __future__ import annotations

import asyncio
import functools
import http
import json
import logging
import signal
from types import FrameType
from typing import Any

import uvicorn
from uvicorn.protocols.http.httptools_impl import HttpToolsProtocol

from service.errors import RequestTimeout
from service.infra.client_board import client_board
from service.infra.logs import uvicorn_log_config
from service.infra.settings import Settings

APP = "service.serving.main:app"
log = logging.getLogger(__name__)


class HeadTimeoutProtocol(HttpToolsProtocol):
    """uvicorn's httptools protocol, closing a connection whose request head is late (408)."""

    def __init__(
        self,
        config: uvicorn.Config,
        server_state: Any,
        app_state: dict[str, Any],
        _loop: asyncio.AbstractEventLoop | None = None,
        *,
        head_timeout: float,
    ) -> None:
        super().__init__(config, server_state, app_state, _loop)
        self._head_timeout = head_timeout
        self._head_timer: asyncio.TimerHandle | None = None

    def connection_made(self, transport: asyncio.Transport) -> None:  # type: ignore[override]
        super().connection_made(transport)
        self._expect_head()

    def on_message_begin(self) -> None:
        super().on_message_begin()
        self._expect_head()

    def on_headers_complete(self) -> None:
        self._head_arrived()
        super().on_headers_complete()

    def connection_lost(self, exc: Exception | None) -> None:
        self._head_arrived()
        super().connection_lost(exc)

    def _expect_head(self) -> None:
        if self._head_timer is None:  # the first request's clock starts with the connection
            self._head_timer = self.loop.call_later(self._head_timeout, self._head_late)

    def _head_arrived(self) -> None:
        if self._head_timer is not None:
            self._head_timer.cancel()
            self._head_timer = None

    def _head_late(self) -> None:
        self._head_timer = None
        if self.transport.is_closing():
            return
        detail = (
            f"the request line and headers did not arrive within {self._head_timeout:g} s"
            " (CKS_HEADER_READ_TIMEOUT_SECONDS)"
        )
        log.info("closed the connection of %s: %s", _peer(self.client), detail)
        if self.cycle is None or self.cycle.response_complete:  # not in the middle of a response
            self.transport.write(_problem_response(RequestTimeout(detail), self.server_state.default_headers))
        self.transport.close()


def _peer(client: tuple[str, int] | None) -> str:
    return f"{client[0]}:{client[1]}" if client else "a client"


def _problem_response(error: RequestTimeout, default_headers: list[tuple[bytes, bytes]]) -> bytes:
    """A complete HTTP/1.1 problem+json response that closes the connection."""
    body = json.dumps(
        {"type": "about:blank", "title": error.title, "status": error.status, "detail": error.detail}
    ).encode()
    head = [f"HTTP/1.1 {error.status} {http.HTTPStatus(error.status).phrase}".encode()]
    head += [name + b": " + value for name, value in default_headers]
    head += [b"content-type: application/problem+json", b"content-length: %d" % len(body)]
    head += [b"connection: close"]
    return b"\r\n".join(head) + b"\r\n\r\n" + body


def uvicorn_options(settings: Settings, host: str | None = None, port: int | None = None) -> dict[str, Any]:
    """The arguments of ``uvicorn.run`` for this service."""
    return {
        "app": APP,
        "host": host or settings.server.host,
        "port": port or settings.server.port,
        "workers": settings.server.workers,
        # A partial of a module-level class: worker processes unpickle it by reference.
        "http": functools.partial(
            HeadTimeoutProtocol, head_timeout=settings.server.header_read_timeout_seconds
        ),
        "limit_concurrency": settings.server.max_connections
        + 1,  # uvicorn counts the request's own connection
        "timeout_graceful_shutdown": settings.server.shutdown_grace_seconds,
        **_logging_options(settings),
    }


def _logging_options(settings: Settings) -> dict[str, Any]:
    """uvicorn's lines in the service's format (the access line is the service's own)."""
    return {"log_config": uvicorn_log_config(settings), "access_log": False}


def serve(settings: Settings, host: str | None = None, port: int | None = None) -> int:
    """Serve until SIGTERM or SIGINT, then stop gracefully; 0 after a graceful stop."""
    previous = signal.signal(signal.SIGTERM, _exit_on_sigterm)
    try:
        with client_board(settings.server.workers):  # before the workers start: they join it
            uvicorn.run(**uvicorn_options(settings, host, port))
    finally:
        signal.signal(signal.SIGTERM, previous)
    return 0


def _exit_on_sigterm(signum: int, frame: FrameType | None) -> None:
    """SIGTERM outside uvicorn's own handler: before the server runs, stop at once; after its
    graceful stop uvicorn raises the signal again for the handler it found (this one), which
    would otherwise be the default action, killing the process (exit status 143, not 0)."""
    raise SystemExit(0)
