"""A real HTTP server on a loopback port between a client and a service: it answers the next
requests as scripted (a 503 with Retry-After, or a connection closed without an answer) and
passes every other request through to the service, recording each one it receives."""

from __future__ import annotations

import json
import threading
import time
from collections import deque
from collections.abc import Iterable
from dataclasses import dataclass
from http.server import BaseHTTPRequestHandler, ThreadingHTTPServer

import httpx

PASSED_BACK = ("content-type", "retry-after", "x-request-id", "location")


@dataclass(frozen=True)
class Unavailable:
    """Answer ``status`` (503, or 429: the client's share) with this Retry-After (None: without one)."""

    retry_after: str | None = "1"
    status: int = 503


@dataclass(frozen=True)
class Drop:
    """Read the request, then close the connection without answering."""


Fault = Unavailable | Drop


@dataclass(frozen=True)
class Seen:
    method: str
    path: str
    request_id: str | None
    at: float


class FaultyProxy:
    def __init__(self, upstream: str, faults: Iterable[Fault] = ()) -> None:
        self.faults: deque[Fault] = deque(faults)
        self.seen: list[Seen] = []
        self._upstream = httpx.Client(base_url=upstream, timeout=60)
        self._server = ThreadingHTTPServer(("127.0.0.1", 0), self._handler())
        self._thread = threading.Thread(target=self._server.serve_forever, daemon=True)

    @property
    def url(self) -> str:
        host, port = self._server.server_address[:2]
        return f"http://{host}:{port}"

    def __enter__(self) -> FaultyProxy:
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._server.shutdown()
        self._server.server_close()
        self._upstream.close()

    def _handler(self) -> type[BaseHTTPRequestHandler]:
        proxy = self

        class Handler(BaseHTTPRequestHandler):
            protocol_version = "HTTP/1.1"  # keep-alive, as the service's

            def do_GET(self) -> None:
                self._handle()

            def do_POST(self) -> None:
                self._handle()

            def log_message(self, format: str, *args: object) -> None:
                pass

            def _handle(self) -> None:
                body = self.rfile.read(int(self.headers.get("Content-Length", 0)))
                proxy.seen.append(
                    Seen(self.command, self.path, self.headers.get("X-Request-ID"), time.monotonic())
                )
                fault = proxy.faults.popleft() if proxy.faults else None
                if isinstance(fault, Drop):
                    self.close_connection = True
                elif isinstance(fault, Unavailable):
                    problem = {
                        "type": "about:blank",
                        "title": "Overloaded",
                        "status": fault.status,
                        "detail": "injected by the test's proxy",
                        "instance": self.path,
                    }
                    retry_after = {} if fault.retry_after is None else {"Retry-After": fault.retry_after}
                    self._answer(
                        fault.status,
                        {"Content-Type": "application/problem+json", **retry_after},
                        json.dumps(problem).encode(),
                    )
                else:
                    self._forward(body)

            def _forward(self, body: bytes) -> None:
                headers = {k: v for k, v in self.headers.items() if k.lower() not in ("host", "connection")}
                answer = proxy._upstream.request(self.command, self.path, headers=headers, content=body)
                passed = {k: v for k, v in answer.headers.items() if k.lower() in PASSED_BACK}
                self._answer(answer.status_code, passed, answer.content)

            def _answer(self, status: int, headers: dict[str, str], body: bytes) -> None:
                self.send_response(status)
                for key, value in headers.items():
                    self.send_header(key, value)
                self.send_header("Content-Length", str(len(body)))
                self.end_headers()
                self.wfile.write(body)

        return Handler
