"""The service under slow clients, a flood, huge images, a zip bomb and SIGTERM: the figures
of docs/operations.md.

    python -m benchmarks.faults_clients

Loopback only, one real ``keypoint-service serve`` process at a time (default settings
unless said), bounded in count and time (about a minute and a half): a normal client's latency
alone and beside 100 slow-body and 100 slow-header connections, and when each kind of slow
client is cut; a polite client (one predict every 0.2 s) alone and beside a flood of 100
connections sending predicts back to back and 100 sending garbage, from another address;
the server's peak resident memory while it refuses a 16-bit RGBA PNG of 6324x6324 (under
the pixel limit), eight at once, and while it decodes accepted 16-bit PNGs; a 7.5 GiB zip bomb;
the time from SIGTERM to exit, idle and with a calibration job and predicts in flight.
Needs the test extras (httpx).

The fault generators here are used by the tests too (tests/live/test_slow_clients.py,
test_fair_admission.py, test_decode_budget.py, test_shutdown.py).
"""

from __future__ import annotations

import argparse
import asyncio
import functools
import io
import itertools
import json
import multiprocessing
import os
import re
import selectors
import signal
import socket
import struct
import sys
import tempfile
import threading
import time
import zipfile
import zlib
from collections import Counter
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass
from pathlib import Path, PurePosixPath
from typing import Any

import cv2
import httpx
import numpy as np

from benchmarks.service_bench.server import Server, serve
from calibration_store import open_store
from service.detector.images import PNG_SIGNATURE, decoded_bytes, read_image_header
from service.infra.settings import DEFAULT_MODEL_DIR, Settings

SAMPLES_DIR = DEFAULT_MODEL_DIR / "samples"
ADMIN_TOKEN = "bench-admin-token-0123456789"
SLOW_BODY_HEAD = (
    b"POST /v1/predict HTTP/1.1\r\nHost: 127.0.0.1\r\nContent-Type: application/json\r\n"
    b"Content-Length: 100000\r\n\r\n"
)
SLOW_HEAD = b"POST /v1/predict HTTP/1.1\r\nHost: 127.0.0.1\r\nX-Padding: " + b"a" * 4000
#: Loopback answers from all of 127.0.0.0/8: the flood's address, another client than 127.0.0.1.
FLOOD_ADDRESS = "127.0.0.2"


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


def polite_client(url: str, seconds: float, interval: float = 0.2) -> tuple[list[float], list[int]]:
    """One predict every ``interval`` seconds (on schedule, or at once when late) for ``seconds``,
    on one keep-alive connection: seconds each took, statuses."""
    image, instances = sample_request()
    seconds_taken, statuses = [], []
    with httpx.Client(base_url=url, timeout=60) as client:
        started = time.monotonic()
        for sent in itertools.count():
            if max(due := started + sent * interval, time.monotonic()) >= started + seconds:
                break
            time.sleep(max(0.0, due - time.monotonic()))
            began = time.perf_counter()
            answer = predict(client, image, instances)
            seconds_taken.append(time.perf_counter() - began)
            statuses.append(answer.status_code)
            if answer.status_code != 200:  # why, for the record
                print(f"polite client: {answer.status_code} {answer.text[:300]}", file=sys.stderr)
    return seconds_taken, statuses


class Flood:
    """``valid`` connections posting predicts of ``instances`` boxes (the most the server takes
    by default: the flood costs the server what it can) back to back and ``garbage`` ones posting
    invalid predicts, all from ``address``, ignoring Retry-After. One event loop in a process of
    its own (so that it takes no turn of this process's interpreter lock) drives them and counts
    the answers: ``statuses`` once it is over (``"error"``: no answer)."""

    def __init__(
        self,
        url: str,
        valid: int,
        garbage: int = 0,
        address: str | tuple[str, ...] = FLOOD_ADDRESS,
        instances: int = 64,
    ) -> None:
        context = multiprocessing.get_context("spawn")
        self._running, self._stop = context.Event(), context.Event()
        self._answers, answers = context.Pipe(duplex=False)
        flood = (url, valid, garbage, address, instances)
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


def _flood(
    url: str, valid: int, garbage: int, address: str | tuple[str, ...], instances: int, *events: Any
) -> None:
    running, stop, answers = events
    statuses: Counter[int | str] = Counter()

    async def post(client: httpx.AsyncClient, files: dict) -> None:
        while not stop.is_set():
            try:
                statuses[(await client.post("/v1/predict", files=files)).status_code] += 1
            except httpx.HTTPError:
                statuses["error"] += 1

    async def run() -> None:
        addresses = (address,) if isinstance(address, str) else address
        limits = httpx.Limits(max_connections=valid + garbage, max_keepalive_connections=valid + garbage)
        # A refusal may come before the body is read: a short timeout ends a send that cannot finish.
        clients = [
            httpx.AsyncClient(
                base_url=url,
                transport=httpx.AsyncHTTPTransport(local_address=local, limits=limits),
                timeout=10,
            )
            for local in addresses
        ]
        image, boxes = sample_request()
        heavy = json.dumps({"instances": (boxes * instances)[:instances]})
        valid_files = {"image": ("image", image), "request": (None, heavy)}
        garbage_files = {"image": ("image", b"not an image"), "request": (None, "{")}
        running.set()
        try:  # connections spread over the addresses in turn
            await asyncio.gather(
                *(post(clients[n % len(clients)], valid_files) for n in range(valid)),
                *(post(clients[n % len(clients)], garbage_files) for n in range(garbage)),
            )
        finally:
            for client in clients:
                await client.aclose()

    asyncio.run(run())
    answers.send(statuses)


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
    return (
        PNG_SIGNATURE
        + png_chunk(b"IHDR", header)
        + png_chunk(b"IDAT", b"".join(idat))
        + png_chunk(b"IEND", b"")
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
    central = struct.pack(
        "<IHHHHHHIIIHHHHHII", 0x02014B50, 45, 45, 0, 8, 0, 0x21, crc, *sizes, 0, 0, 0, 0, local_at
    )
    new_directory_at = local_at + len(local) + len(encoded) + len(zip64) + len(data)
    directory = small[directory_at:end] + central + encoded + zip64
    eocd = struct.pack("<IHHHHIIH", 0x06054B50, 0, 0, 2, 2, len(directory), new_directory_at, 0)
    return small[:directory_at] + local + encoded + zip64 + data + directory + eocd


def long_batch(copies: int) -> bytes:
    """A COCO zip of the bundled samples ``copies`` times over, each copy re-encoded at another
    JPEG quality so that no two files are the same (repeats would be refused)."""
    doc = json.loads((SAMPLES_DIR / "annotations.json").read_text())
    images, annotations = list(doc["images"]), list(doc["annotations"])
    files = {image["file_name"]: (SAMPLES_DIR / image["file_name"]).read_bytes() for image in images}
    next_image = max(image["id"] for image in images) + 1
    next_annotation = max(a["id"] for a in annotations) + 1
    for copy in range(1, copies):
        for image in images:
            path = PurePosixPath(image["file_name"])
            name = str(path.with_name(f"copy{copy}-{path.name}"))
            pixels = cv2.imdecode(np.frombuffer(files[image["file_name"]], np.uint8), cv2.IMREAD_COLOR)
            quality = [cv2.IMWRITE_JPEG_QUALITY, 95 - copy % 60]
            files[name] = cv2.imencode(".jpg", pixels, quality)[1].tobytes()
            doc["images"].append({**image, "id": next_image, "file_name": name})
            for annotation in (a for a in annotations if a["image_id"] == image["id"]):
                doc["annotations"].append({**annotation, "id": next_annotation, "image_id": next_image})
                next_annotation += 1
            next_image += 1
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w") as archive:
        archive.writestr("annotations.json", json.dumps(doc))
        for name, data in files.items():
            archive.writestr(name, data)
    return buffer.getvalue()


# ---------------------------------------------------------------- the benchmark


def _mib(count: float) -> str:
    return f"{count / 2**20:.0f} MiB"


def _ms(seconds: list[float]) -> str:
    return f"p50 {1000 * percentile(seconds, 50):.1f} ms, p99 {1000 * percentile(seconds, 99):.1f} ms"


def _counted(statuses: list[int | None]) -> str:
    return ", ".join(f"{statuses.count(s)} x {s}" for s in sorted(set(statuses), key=str))


def _post_all(url: str, image: bytes, instances: list[dict], count: int) -> list[int]:
    """``count`` predicts at once, each on its own connection: their statuses."""

    def post(_: int) -> int:
        with httpx.Client(base_url=url, timeout=120) as client:
            return predict(client, image, instances).status_code

    with ThreadPoolExecutor(count) as pool:
        return list(pool.map(post, range(count)))


def slow_clients(server: Server, requests: int, slow: int) -> None:
    predict_latencies(server.url, 5)  # warm-up
    alone, statuses = predict_latencies(server.url, requests)
    print(f"normal client alone ({requests} predicts in a row): {_ms(alone)}; {_counted(statuses)}")
    with SlowClients(int(server.url.rsplit(":", 1)[1]), bodies=slow, heads=slow) as clients:
        beside, statuses = predict_latencies(server.url, requests)
        still_open = clients.open_count()
        clients.wait_closed(timeout=60)
    print(
        f"beside {slow} slow-body + {slow} slow-header connections (a byte every 0.5 s; {still_open}"
        f" still open when it was done): {_ms(beside)}; {_counted(statuses)}"
    )
    for kind, name in (("body", "slow-body"), ("head", "slow-header")):
        cut = [c.closed_after for c in clients.of(kind) if c.closed_after is not None]
        when = f"after {min(cut):.1f} to {max(cut):.1f} s" if cut else ""
        print(
            f"  {name} connections: {len(cut)} of {slow} closed by the server {when};"
            f" answers {_counted([c.status for c in clients.of(kind)])}"
        )


def flood(server: Server, seconds: float, valid: int, garbage: int, addresses: int = 1) -> None:
    """The polite client alone, then beside ``valid`` + ``garbage`` flood connections from one
    address (FLOOD_ADDRESS) or spread over ``addresses`` (127.0.1.1, 127.0.1.2, ...)."""
    polite_client(server.url, 2)  # warm-up
    alone, statuses = polite_client(server.url, seconds / 2)
    print(
        f"polite client alone (a predict every 0.2 s, {seconds / 2:g} s): {_ms(alone)}; {_counted(statuses)}"
    )
    spread = tuple(f"127.0.1.{n}" for n in range(1, addresses + 1)) if addresses > 1 else FLOOD_ADDRESS
    origin = FLOOD_ADDRESS if addresses == 1 else f"{addresses} addresses"
    with Flood(server.url, valid, garbage, spread) as flooding:
        time.sleep(1)  # the flood takes every place it can
        beside, statuses = polite_client(server.url, seconds)
    ok = statuses.count(200) / len(statuses)
    print(
        f"beside a flood from {origin} ({valid} connections posting predicts of 64 boxes back to"
        f" back, {garbage}"
        f" posting garbage) for {seconds:g} s: {100 * ok:.0f} % answered 200, {_ms(beside)}"
        f" ({percentile(beside, 99) / percentile(alone, 99):.1f}x alone); {_counted(statuses)}"
    )
    print(f"  the flood's answers: {_counted(list(flooding.statuses.elements()))}")


def huge_images(server: Server, settings: Settings) -> None:
    instances = sample_request()[1][:1]
    budget = f"CKS_MAX_DECODED_BYTES {_mib(settings.predict.max_decoded_bytes)}"
    for name, image in (
        ("16-bit RGBA PNG 6324x6324 (the issue's)", flat_png(6324, 6324)),
        ("16-bit RGBA PNG 4000x4000", flat_png(4000, 4000)),
    ):
        needed = decoded_bytes(image, read_image_header(image))
        started = time.perf_counter()
        rise, statuses = peak_while(server.pid, functools.partial(_post_all, server.url, image, instances, 1))
        took = time.perf_counter() - started
        print(
            f"{name}: {_mib(needed)} to decode ({budget}): {_counted(statuses)} in {took:.2f} s,"
            f" peak RSS +{_mib(rise)}"
        )
        rise, statuses = peak_while(server.pid, functools.partial(_post_all, server.url, image, instances, 8))
        print(
            f"  8 at once: {_counted(statuses)}, peak RSS +{_mib(rise)}"
            f" (at most CKS_CPU_WORKERS = {settings.model.cpu_workers} decode at once)"
        )


def bomb(server: Server, data_dir: Path) -> None:
    body = zip_bomb(15 * 2**29)
    headers = {"Authorization": f"Bearer {ADMIN_TOKEN}", "Content-Type": "application/zip"}
    with httpx.Client(base_url=server.url, timeout=120) as client:
        started = time.perf_counter()
        response = client.post("/v1/admin/calibrations", content=body, headers=headers)
        took = time.perf_counter() - started
    left = [p for folder in ("jobs", "uploads") for p in (data_dir / folder).rglob("*") if p.is_file()]
    print(
        f"zip bomb of 7.5 GiB ({_mib(len(body))} zipped): {response.status_code} in {took:.2f} s,"
        f" {sum(p.stat().st_size for p in left)} bytes left on disk"
    )


def annotations_bomb(count: int) -> bytes:
    """The samples' first image and ``count`` copies of its first annotation (deflated: tiny)."""
    doc = json.loads((SAMPLES_DIR / "annotations.json").read_text())
    image, first = doc["images"][0], doc["annotations"][0]
    doc["images"], doc["annotations"] = [image], [{**first, "id": n + 1} for n in range(count)]
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w", zipfile.ZIP_DEFLATED) as archive:
        archive.writestr("annotations.json", json.dumps(doc))
        archive.writestr(image["file_name"], (SAMPLES_DIR / image["file_name"]).read_bytes())
    return buffer.getvalue()


def many_annotations(server: Server) -> None:
    """200,000 annotations in a small zip, refused while a polite client predicts."""
    body = annotations_bomb(200_000)
    headers = {"Authorization": f"Bearer {ADMIN_TOKEN}", "Content-Type": "application/zip"}
    with httpx.Client(base_url=server.url, timeout=120) as client, ThreadPoolExecutor(1) as pool:
        polite = pool.submit(polite_client, server.url, 6.0)
        time.sleep(1)

        def refuse() -> tuple[int, float]:
            started = time.perf_counter()
            status = client.post("/v1/admin/calibrations", content=body, headers=headers).status_code
            return status, time.perf_counter() - started

        rise, (status, took) = peak_while(server.pid, refuse)
        seconds, statuses = polite.result()
    print(
        f"200,000 annotations ({_mib(len(body))} zipped): {status} in {took:.2f} s, peak RSS +{_mib(rise)};"
        f" a predict every 0.2 s meanwhile: max {max(seconds) * 1000:.0f} ms, {_counted(statuses)}"
    )


def sigterm(settings: dict[str, str], busy: bool) -> None:
    """Time from SIGTERM to exit, idle or with a calibration job scoring and 8 predicts in flight."""
    with tempfile.TemporaryDirectory(prefix="cks-faults-") as data_dir, ThreadPoolExecutor(8) as pool:
        with serve({**settings, "CKS_DATA_DIR": data_dir}) as server:
            predicts, job_id = [], None
            if busy:
                with httpx.Client(base_url=server.url, timeout=120) as client:
                    job_id = client.post(
                        "/v1/admin/calibrations",
                        content=long_batch(30),
                        params={"activate": "true", "force": "true", "reason": "benchmark"},
                        headers={"Authorization": f"Bearer {ADMIN_TOKEN}", "Content-Type": "application/zip"},
                    ).json()["id"]
                time.sleep(2)  # the job scores meanwhile
                image, instances = sample_request()
                heavy = (instances * 16)[:64]
                predicts = [pool.submit(_post_all, server.url, image, heavy, 1) for _ in range(8)]
                deadline = time.monotonic() + 30
                while metric(server.url, "cks_predict_in_flight") < 8 and time.monotonic() < deadline:
                    time.sleep(0.01)  # until the server has received them all
            sent = time.perf_counter()
            os.kill(server.pid, signal.SIGTERM)
            _, status = os.waitpid(server.pid, 0)  # reaped here to time it (serve() copes)
            took = time.perf_counter() - sent
        line = f"exit {os.waitstatus_to_exitcode(status)} after {took:.2f} s"
        if not busy:
            print(f"SIGTERM, idle: {line}")
            return
        with open_store(f"sqlite:///{data_dir}/calibrations.db") as store:
            job = store.get_job(job_id)
        statuses = [status for future in predicts for status in future.result()]
        print(
            f"SIGTERM with a calibration job scoring and 8 predicts (64 instances each) in flight: {line};"
            f" predicts {_counted(statuses)}; job {job.state} at {job.done}/{job.total}"
        )


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(prog="python -m benchmarks.faults_clients")
    parser.add_argument("--requests", type=int, default=40, help="normal predicts per measurement")
    parser.add_argument("--slow", type=int, default=100, help="slow-body and slow-header connections, each")
    parser.add_argument("--flood-seconds", type=float, default=20, help="the polite client beside the flood")
    parser.add_argument("--flood", type=int, default=100, help="flood connections posting predicts")
    parser.add_argument("--garbage", type=int, default=100, help="flood connections posting garbage")
    parser.add_argument("--only-flood", action="store_true", help="the flood alone, no other measurement")
    parser.add_argument("--flood-addresses", type=int, default=1, help="addresses the flood is spread over")
    args = parser.parse_args(argv)
    settings = {"CKS_ADMIN_TOKEN": ADMIN_TOKEN, "CKS_MODEL_DIR": str(DEFAULT_MODEL_DIR)}
    print(f"default settings, {os.cpu_count()} cores, loopback; RSS: the server's peak VmHWM, reset per step")
    with (
        tempfile.TemporaryDirectory(prefix="cks-faults-") as data_dir,
        serve({**settings, "CKS_DATA_DIR": data_dir}) as server,
    ):
        flood(server, args.flood_seconds, args.flood, args.garbage, args.flood_addresses)
        if args.only_flood:
            return 0
        slow_clients(server, args.requests, args.slow)
        huge_images(server, Settings())
        bomb(server, Path(data_dir))
        many_annotations(server)
    sigterm(settings, busy=False)
    sigterm(settings, busy=True)
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
