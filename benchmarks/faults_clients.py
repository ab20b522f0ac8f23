"""Faults for tests and benchmarks, loopback only: slow clients (connections trickling their
request heads or bodies) and a normal client timing its predicts; huge PNGs and a server's
peak resident memory; zip bombs. Used by tests/service/test_slow_clients.py,
test_decode_budget.py and tests/inputs/.
"""

from __future__ import annotations

import io
import json
import re
import selectors
import socket
import struct
import threading
import time
import zipfile
import zlib
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path
from typing import Any

import httpx
import numpy as np

from service.image_decoding import PNG_SIGNATURE
from service.settings import DEFAULT_MODEL_DIR

SAMPLES_DIR = DEFAULT_MODEL_DIR / "samples"
SLOW_BODY_HEAD = (
    b"POST /v1/predict HTTP/1.1\r\nHost: 127.0.0.1\r\nContent-Type: application/json\r\n"
    b"Content-Length: 100000\r\n\r\n"
)
SLOW_HEAD = b"POST /v1/predict HTTP/1.1\r\nHost: 127.0.0.1\r\nX-Padding: " + b"a" * 4000


# ---------------------------------------------------------------- slow clients


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


# ---------------------------------------------------------------- a normal client


def sample_request() -> tuple[bytes, list[dict]]:
    """The first sample image and its labeled instances."""
    doc = json.loads((SAMPLES_DIR / "annotations.json").read_text())
    image = doc["images"][0]
    names = {c["id"]: c["name"] for c in doc["categories"]}
    instances = [{"object": names[a["category_id"]], "bbox": a["bbox"]}
                 for a in doc["annotations"] if a["image_id"] == image["id"]]  # fmt: skip
    return (SAMPLES_DIR / image["file_name"]).read_bytes(), instances


def predict(client: httpx.Client, image: bytes, instances: list[dict]) -> httpx.Response:
    """POST /v1/predict as multipart."""
    files = {"image": ("image", image), "request": (None, json.dumps({"instances": instances}))}
    return client.post("/v1/predict", files=files)


def predict_latencies(url: str, count: int) -> tuple[list[float], list[int]]:
    """``count`` predicts, one after the other on one keep-alive connection: seconds, statuses."""
    image, instances = sample_request()
    seconds, statuses = [], []
    with httpx.Client(base_url=url, timeout=60) as client:
        for _ in range(count):
            started = time.perf_counter()
            statuses.append(predict(client, image, instances).status_code)
            seconds.append(time.perf_counter() - started)
    return seconds, statuses


def metric(url: str, name: str, labels: str = "") -> float:
    """A sample of a server's /metrics (0 when absent)."""
    text = httpx.get(f"{url}/metrics", timeout=30).text
    match = re.search(rf"^{name}{re.escape(labels)} ([0-9.e+-]+)$", text, re.MULTILINE)
    return float(match.group(1)) if match else 0.0


def percentile(values: list[float], q: float) -> float:
    return float(np.percentile(values, q))


# ---------------------------------------------------------------- huge images


def flat_png(width: int, height: int, depth: int = 16, colour_type: int = 6) -> bytes:
    """A valid PNG of a repeated striped row: huge once decoded, small on the wire (one row is
    compressed at a time, so building it needs little memory)."""
    channels = {0: 1, 2: 3, 4: 2, 6: 4}[colour_type]
    stripes = np.arange(width * channels, dtype=np.uint32) % 251 * 257
    row = b"\x00" + stripes.astype(">u2" if depth == 16 else np.uint8).tobytes()
    compressor, idat = zlib.compressobj(6), []
    for _ in range(height):
        idat.append(compressor.compress(row))
    idat.append(compressor.flush())
    header = struct.pack(">IIBBBBB", width, height, depth, colour_type, 0, 0, 0)
    return PNG_SIGNATURE + png_chunk(b"IHDR", header) + png_chunk(b"IDAT", b"".join(idat)) + png_chunk(
        b"IEND", b""
    )


def png_chunk(kind: bytes, payload: bytes) -> bytes:
    return struct.pack(">I", len(payload)) + kind + payload + struct.pack(">I", zlib.crc32(kind + payload))


def peak_rss_bytes(pid: int) -> int:
    """The peak resident memory of a process since its last ``reset_peak_rss`` (VmHWM)."""
    status = Path(f"/proc/{pid}/status").read_text()
    return 1024 * int(next(line.split()[1] for line in status.splitlines() if line.startswith("VmHWM:")))


def reset_peak_rss(pid: int) -> None:
    Path(f"/proc/{pid}/clear_refs").write_text("5")


def peak_while(pid: int, action: Callable[[], Any]) -> tuple[int, Any]:
    """The rise of the process's peak resident memory while ``action()`` runs, and its result."""
    reset_peak_rss(pid)
    before = peak_rss_bytes(pid)
    result = action()
    return peak_rss_bytes(pid) - before, result


# ---------------------------------------------------------------- uploads


def zip_bomb(uncompressed: int, name: str = "images/bomb.png") -> bytes:
    """A real zip bomb: ``annotations.json`` and one member of ``uncompressed`` zero bytes (a
    multiple of 16 MiB) with honest headers, deflated to about a thousandth of that."""
    block = 1 << 24
    assert uncompressed % block == 0, "a multiple of 16 MiB"
    compressor = zlib.compressobj(9, zlib.DEFLATED, -15)
    # After a full flush no block refers back to earlier data, so the same bytes can repeat.
    unit = compressor.compress(bytes(block)) + compressor.flush(zlib.Z_FULL_FLUSH)
    data = unit * (uncompressed // block) + compressor.flush()
    crc = 0
    for _ in range(uncompressed // block):
        crc = zlib.crc32(bytes(block), crc)
    annotations = json.dumps({"images": [], "annotations": [], "categories": []}).encode()
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w") as archive:
        archive.writestr("annotations.json", annotations)
    small = buffer.getvalue()
    end = small.rindex(b"PK\x05\x06")
    directory_at = struct.unpack("<I", small[end + 16 : end + 20])[0]
    local_at = directory_at
    encoded = name.encode()
    zip64 = struct.pack("<HHQQ", 1, 16, uncompressed, len(data))
    sizes = (0xFFFFFFFF, 0xFFFFFFFF, len(encoded), len(zip64))  # the real ones are in the zip64 field
    local = struct.pack("<IHHHHHIIIHH", 0x04034B50, 45, 0, 8, 0, 0x21, crc, *sizes)
    central = struct.pack("<IHHHHHHIIIHHHHHII", 0x02014B50, 45, 45, 0, 8, 0, 0x21, crc, *sizes, 0, 0, 0, 0,
                          local_at)  # fmt: skip
    new_directory_at = local_at + len(local) + len(encoded) + len(zip64) + len(data)
    directory = small[directory_at:end] + central + encoded + zip64
    eocd = struct.pack("<IHHHHIIH", 0x06054B50, 0, 0, 2, 2, len(directory), new_directory_at, 0)
    return small[:directory_at] + local + encoded + zip64 + data + directory + eocd
