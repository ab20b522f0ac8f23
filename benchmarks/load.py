"""Clients that load a real server on loopback, for the live tests: a polite client timing its
predicts, a flood of keep-alive connections from chosen addresses, slow clients, and /metrics.

Loopback answers from all of 127.0.0.0/8, so each address there is another client to the server.
"""

from __future__ import annotations

import asyncio
import itertools
import json
import multiprocessing
import re
import selectors
import socket
import threading
import time
from collections import Counter
from collections.abc import Sequence
from dataclasses import dataclass
from typing import Any

import httpx

from service.infra.settings import DEFAULT_MODEL_DIR

SAMPLES_DIR = DEFAULT_MODEL_DIR / "samples"
FLOOD_ADDRESS = "127.0.0.2"


def sample_request() -> tuple[bytes, list[dict]]:
    """The first sample image and its labeled instances."""
    doc = json.loads((SAMPLES_DIR / "annotations.json").read_text())
    image = doc["images"][0]
    names = {c["id"]: c["name"] for c in doc["categories"]}
    instances = [
        {"object": names[a["category_id"]], "bbox": a["bbox"]}
        for a in doc["annotations"]
        if a["image_id"] == image["id"]
    ]
    return (SAMPLES_DIR / image["file_name"]).read_bytes(), instances


def predict(client: httpx.Client, image: bytes, instances: list[dict]) -> httpx.Response:
    """POST /v1/predict as multipart."""
    files = {"image": ("image", image), "request": (None, json.dumps({"instances": instances}))}
    return client.post("/v1/predict", files=files)


def _client(url: str, address: str | None, token: str | None, timeout: float = 60) -> httpx.Client:
    headers = {"Authorization": f"Bearer {token}"} if token else {}
    transport = httpx.HTTPTransport(local_address=address)
    return httpx.Client(base_url=url, transport=transport, headers=headers, timeout=timeout)


def predict_latencies(url: str, count: int) -> tuple[list[float], list[int]]:
    """``count`` predicts, one after the other on one keep-alive connection: seconds, statuses."""
    image, instances = sample_request()
    seconds, statuses = [], []
    with _client(url, None, None) as client:
        for _ in range(count):
            started = time.perf_counter()
            statuses.append(predict(client, image, instances).status_code)
            seconds.append(time.perf_counter() - started)
    return seconds, statuses


def polite_client(
    url: str, seconds: float, interval: float = 0.2, address: str | None = None, token: str | None = None
) -> tuple[list[float], list[int]]:
    """One predict every ``interval`` seconds (on schedule, or at once when late) for ``seconds``,
    on one keep-alive connection from ``address`` with ``token`` when given: seconds each took,
    statuses."""
    image, instances = sample_request()
    taken, statuses = [], []
    with _client(url, address, token) as client:
        started = time.monotonic()
        for sent in itertools.count():
            if max(due := started + sent * interval, time.monotonic()) >= started + seconds:
                break
            time.sleep(max(0.0, due - time.monotonic()))
            began = time.perf_counter()
            statuses.append(predict(client, image, instances).status_code)
            taken.append(time.perf_counter() - began)
    return taken, statuses


def metric(url: str, name: str, labels: str = "") -> float:
    """A sample of a server's /metrics (0 when absent)."""
    text = httpx.get(f"{url}/metrics", timeout=30).text
    match = re.search(rf"^{name}{re.escape(labels)} ([0-9.e+-]+)$", text, re.MULTILINE)
    return float(match.group(1)) if match else 0.0


# ---------------------------------------------------------------- a flood


class Flood:
    """``connections`` keep-alive connections, connection n from ``addresses[n % len(addresses)]``
    (in 127.0.0.0/8), each posting predicts of ``instances`` boxes back to back, ignoring
    Retry-After, with ``Authorization: Bearer <token>`` when given, until the block ends.
    ``statuses`` counts the answers once it is over (``"error"``: no answer). One event loop in a
    process of its own drives them, so that it takes no turn of this process's interpreter lock."""

    def __init__(
        self,
        url: str,
        connections: int,
        addresses: Sequence[str] = (FLOOD_ADDRESS,),
        token: str | None = None,
        instances: int = 64,
    ) -> None:
        context = multiprocessing.get_context("spawn")
        self._running, self._stop = context.Event(), context.Event()
        self._answers, answers = context.Pipe(duplex=False)
        flood = (url, connections, tuple(addresses), token, instances)
        self._process = context.Process(
            target=_flood, args=(*flood, self._running, self._stop, answers), daemon=True
        )
        self.statuses: Counter[int | str] = Counter()

    def __enter__(self) -> Flood:
        self._process.start()
        if not self._running.wait(60):
            self._process.kill()
            raise RuntimeError("the flood's process did not start within 60 s")
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        if self._answers.poll(60):  # each connection ends its request first (10 s at most)
            self.statuses = self._answers.recv()
        self._process.kill()
        self._process.join()


def flood(url: str, connections: int, seconds: float, **options: Any) -> Counter[int | str]:
    """A ``Flood`` (same options) for ``seconds``: the statuses it got."""
    with Flood(url, connections, **options) as flooding:
        time.sleep(seconds)
    return flooding.statuses


def _flood(
    url: str, connections: int, addresses: tuple[str, ...], token: str | None, instances: int, *events: Any
) -> None:
    running, stop, answers = events
    statuses: Counter[int | str] = Counter()
    image, boxes = sample_request()
    files = {
        "image": ("image", image),
        "request": (None, json.dumps({"instances": (boxes * instances)[:instances]})),
    }
    headers = {"Authorization": f"Bearer {token}"} if token else {}

    async def post(address: str) -> None:
        # One connection each; a refusal may come before the body is read: a short timeout ends a
        # send that cannot finish.
        transport = httpx.AsyncHTTPTransport(local_address=address, limits=httpx.Limits(max_connections=1))
        async with httpx.AsyncClient(
            base_url=url, transport=transport, headers=headers, timeout=10
        ) as client:
            while not stop.is_set():
                try:
                    statuses[(await client.post("/v1/predict", files=files)).status_code] += 1
                except httpx.HTTPError:
                    statuses["error"] += 1

    async def run() -> None:
        running.set()
        await asyncio.gather(*(post(addresses[n % len(addresses)]) for n in range(connections)))

    asyncio.run(run())
    answers.send(statuses)


# ---------------------------------------------------------------- slow clients

SLOW_BODY_HEAD = (
    b"POST /v1/predict HTTP/1.1\r\nHost: 127.0.0.1\r\nContent-Type: application/json\r\n"
    b"Content-Length: 100000\r\n\r\n"
)
SLOW_HEAD = b"POST /v1/predict HTTP/1.1\r\nHost: 127.0.0.1\r\nX-Padding: " + b"a" * 4000


@dataclass
class _Connection:
    sock: socket.socket
    kind: str
    pending: bytes
    opened: float
    answer: bytes = b""
    closed_after: float | None = None

    @property
    def status(self) -> int | None:
        """The status code of the server's answer (None: it closed without one)."""
        parts = self.answer.split(b" ", 2)
        return int(parts[1]) if len(parts) > 1 and parts[1].isdigit() else None


class SlowClients:
    """Loopback connections sending their request one byte every ``interval`` seconds: ``heads``
    trickle a request line and headers, ``bodies`` send a whole predict head at once and then
    trickle its body. A thread drives them all and records what the server answers each one
    and when it closes it."""

    def __init__(self, port: int, bodies: int, heads: int, interval: float = 0.5) -> None:
        self._port, self._interval = port, interval
        self._counts = {"body": bodies, "head": heads}
        self.connections: list[_Connection] = []
        self._selector = selectors.DefaultSelector()
        self._stop = threading.Event()
        self._thread = threading.Thread(target=self._drive, name="slow-clients", daemon=True)

    def __enter__(self) -> SlowClients:
        for kind, count in self._counts.items():
            for _ in range(count):
                sock = socket.create_connection(("127.0.0.1", self._port), timeout=10)
                first = SLOW_BODY_HEAD if kind == "body" else b""
                rest = b'{"instances": [' + b" " * 99_000 if kind == "body" else SLOW_HEAD
                sock.sendall(first)
                connection = _Connection(sock, kind, rest, time.monotonic())
                self.connections.append(connection)
                self._selector.register(sock, selectors.EVENT_READ, connection)
        self._thread.start()
        return self

    def __exit__(self, *exc: object) -> None:
        self._stop.set()
        self._thread.join()
        for connection in self.connections:
            connection.sock.close()
        self._selector.close()

    def _drive(self) -> None:
        while not self._stop.is_set():
            for connection in self.connections:
                if connection.closed_after is None and connection.pending:
                    try:
                        connection.sock.send(connection.pending[:1])
                        connection.pending = connection.pending[1:]
                    except OSError:
                        pass  # closed by the server: the read below records it
            deadline = time.monotonic() + self._interval
            while (left := deadline - time.monotonic()) > 0 and not self._stop.is_set():
                for key, _ in self._selector.select(left):
                    self._read(key.data)

    def _read(self, connection: _Connection) -> None:
        try:
            data = connection.sock.recv(65536)
        except OSError:
            data = b""
        if data:
            connection.answer += data
            return
        connection.closed_after = time.monotonic() - connection.opened
        self._selector.unregister(connection.sock)

    def open_count(self) -> int:
        return sum(1 for c in self.connections if c.closed_after is None)

    def wait_closed(self, timeout: float) -> bool:
        """Wait until the server has closed every connection; False on timeout."""
        deadline = time.monotonic() + timeout
        while self.open_count() and time.monotonic() < deadline:
            time.sleep(0.05)
        return not self.open_count()

    def of(self, kind: str) -> list[_Connection]:
        return [c for c in self.connections if c.kind == kind]
