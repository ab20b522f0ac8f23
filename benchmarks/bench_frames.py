"""A camera frame in memory to the parsed answer, one request at a time, side by side.

    python -m benchmarks.bench_frames              # 4 sizes x 1 and 4 boxes, 15 rounds; docs/performance.md
    python -m benchmarks.bench_frames --rounds 3 --sizes 640x480 --output /tmp/p.md   # a smoke run

Frames of 640x480, 1280x720, 1920x1080 and 3840x2160 (the samples folder's busiest image scaled
to the height, the rest of the width its mirror image), 1 and 4 boxes, concurrency 1, keep-alive
connections. Each round sends, in turn: the service with the boxes' regions as raw pixels and as
JPEG (POST /v1/predict/frame, the client's ``frame_parts``), the service with the whole frame as
JPEG (POST /v1/predict), the plain FastAPI peer (benchmarks/peers/fastapi_app.py, the fastest peer
at concurrency 1 in bench_peers) with the whole JPEG, and through the Python client
``predict(frame)`` against JPEG encode + ``predict(jpeg bytes)``. Every time includes the
client's encoding and the parsing of the answer. Before timing: the raw regions' answer must be
the whole frame's (PNG) byte for byte, and the peer's the service's for the same JPEG.
Writes the ``bench_frames`` section of docs/performance.md.
"""

from __future__ import annotations

import argparse
import json
import os
import statistics
import sys
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

import cv2
import httpx
import numpy as np

from benchmarks.peers.answers import difference
from benchmarks.peers.servers import PEERS, SERVICE
from benchmarks.service_bench import page
from benchmarks.service_bench.inputs import Sample, load_sample
from benchmarks.service_bench.machine import this_machine
from service.infra.settings import DEFAULT_MODEL_DIR

ROOT = Path(__file__).resolve().parents[1]
sys.path.insert(0, str(ROOT / "client"))  # this checkout's client, not an installed copy

from keypoint_client import KeypointClient  # noqa: E402
from keypoint_client.frames import frame_parts, jpeg_bytes  # noqa: E402

DEFAULT_OUTPUT = ROOT / "docs" / "performance.md"
SIZES = ((640, 480), (1280, 720), (1920, 1080), (3840, 2160))
BOXES = (1, 4)
PEER = next(peer for peer in PEERS if peer.name == "FastAPI")
CONTENDERS = (
    "service, raw regions",
    "service, JPEG regions",
    "service, whole JPEG",
    "FastAPI, whole JPEG",
    "client predict(frame)",
    "client JPEG + predict",
)
Send = Callable[[], object]


def log(message: str) -> None:
    print(message, flush=True)


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rounds", type=int, default=15, help="timed requests per contender and point")
    parser.add_argument(
        "--sizes", default=",".join(f"{w}x{h}" for w, h in SIZES), help="e.g. 640x480,1920x1080"
    )
    parser.add_argument("--output", type=Path, default=DEFAULT_OUTPUT)
    args = parser.parse_args(argv)
    args.sizes = [tuple(int(v) for v in size.split("x")) for size in args.sizes.split(",")]
    return args


@dataclass(frozen=True)
class Point:
    """One frame size and box count: the frame (RGB) and the request's parameters."""

    width: int
    height: int
    boxes: int
    frame: np.ndarray
    parameters: dict

    @property
    def name(self) -> str:
        return f"{self.width}x{self.height}, {self.boxes} box{'es' if self.boxes > 1 else ''}"


def make_point(sample: Sample, width: int, height: int, boxes: int) -> Point:
    """The sample scaled to the frame's height at its left, its mirror image filling the rest."""
    bgr = cv2.imdecode(np.frombuffer(sample.jpeg, np.uint8), cv2.IMREAD_COLOR)
    scale = height / bgr.shape[0]
    scaled = cv2.resize(bgr, (round(bgr.shape[1] * scale), height), interpolation=cv2.INTER_LINEAR)
    mirrored = np.concatenate([scaled, scaled[:, ::-1]] * (1 + width // (2 * scaled.shape[1])), axis=1)
    frame = np.ascontiguousarray(mirrored[:, :width, ::-1])  # RGB, as a camera driver gives it
    chosen = sample.with_instances(boxes)
    instances = [{**i, "bbox": [v * scale for v in i["bbox"]]} for i in chosen.instances]
    return Point(width, height, boxes, frame, {"instances": instances})


class Contenders:
    """How each contender sends one point's frame and parses the answer."""

    def __init__(self, service: str, peer: str, padding: float) -> None:
        self.http = httpx.Client(base_url=service, timeout=120)
        self.peer = httpx.Client(base_url=peer, timeout=120)
        self.client = KeypointClient(service, timeout=120)
        self.padding = padding

    def close(self) -> None:
        for closable in (self.http, self.peer, self.client):
            closable.close()

    def regions(self, point: Point, sending: str = "regions") -> dict:
        files = frame_parts(point.frame, point.parameters, self.padding, sending)  # type: ignore[arg-type]
        return _answer(self.http.post("/v1/predict/frame", files=files))

    def whole_jpeg(self, point: Point, http: httpx.Client) -> dict:
        files = {"image": ("frame.jpg", jpeg_bytes(point.frame), "image/jpeg")}
        return _answer(http.post("/v1/predict", files=files, data={"request": json.dumps(point.parameters)}))

    def sends(self, point: Point) -> dict[str, Send]:
        instances = point.parameters["instances"]
        return {
            CONTENDERS[0]: lambda: self.regions(point),
            CONTENDERS[1]: lambda: self.regions(point, "jpeg-regions"),
            CONTENDERS[2]: lambda: self.whole_jpeg(point, self.http),
            CONTENDERS[3]: lambda: self.whole_jpeg(point, self.peer),
            CONTENDERS[4]: lambda: self.client.predict(point.frame, instances),
            CONTENDERS[5]: lambda: self.client.predict(jpeg_bytes(point.frame), instances),
        }

    def check(self, point: Point) -> None:
        """Raw regions answer as the whole frame's PNG, byte for byte; the peer as the service."""
        files = frame_parts(point.frame, point.parameters, self.padding, "raw-frame")
        whole = self.http.post("/v1/predict/frame", files=files).content
        regions = frame_parts(point.frame, point.parameters, self.padding, "regions")
        if self.http.post("/v1/predict/frame", files=regions).content != whole:
            raise SystemExit(f"{point.name}: the raw regions' answer is not the whole frame's")
        why = difference(self.whole_jpeg(point, self.http), self.whole_jpeg(point, self.peer))
        if why is not None:
            raise SystemExit(f"{point.name}: the peer's answer differs from the service's: {why}")


def _answer(response: httpx.Response) -> dict:
    response.raise_for_status()
    return response.json()


def measure(contenders: Contenders, points: list[Point], rounds: int) -> dict[tuple[str, str], list[float]]:
    """Milliseconds per request, the contenders taking turns within each round (paired)."""
    times: dict[tuple[str, str], list[float]] = {}
    for point in points:
        contenders.check(point)
        sends = contenders.sends(point)
        for send in sends.values():  # warm: connections, first runs of each batch size
            send()
        for _ in range(rounds):
            for name, send in sends.items():
                started = time.perf_counter()
                send()
                times.setdefault((point.name, name), []).append(1000 * (time.perf_counter() - started))
        log(
            f"{point.name}: " + ", ".join(f"{n} {statistics.median(times[point.name, n]):.1f}" for n in sends)
        )
    return times


def _cell(values: list[float]) -> str:
    quartiles = statistics.quantiles(values, n=4) if len(values) > 1 else [values[0]] * 3
    return f"{quartiles[1]:.1f} ({quartiles[0]:.1f}-{quartiles[2]:.1f})"


def render(command: str, machine: str, points: list[Point], times: dict, rounds: int, load_after: str) -> str:
    def median(point: Point, name: str) -> float:
        return statistics.median(times[point.name, name])

    header = "| frame, boxes | " + " | ".join(CONTENDERS) + " |"
    rows = [header, "|" + "---|" * (len(CONTENDERS) + 1)]
    rows += [
        f"| {p.name} | " + " | ".join(_cell(times[p.name, n]) for n in CONTENDERS) + " |" for p in points
    ]
    ratios = [
        "| frame, boxes | FastAPI whole JPEG / service raw regions | service whole JPEG / raw regions"
        " | client JPEG + predict / client predict(frame) |",
        "|---|---|---|---|",
    ]
    for p in points:
        peer, whole, raw = median(p, CONTENDERS[3]), median(p, CONTENDERS[2]), median(p, CONTENDERS[0])
        client = median(p, CONTENDERS[5]) / median(p, CONTENDERS[4])
        ratios.append(f"| {p.name} | **{peer / raw:.2f}** | {whole / raw:.2f} | **{client:.2f}** |")
    return "\n".join(
        [
            "## A camera frame to sets (bench_frames)",
            "",
            f"`{command}`: {machine}; load average after the run {load_after}. Milliseconds from a frame in"
            f" memory (RGB) to the parsed answer, median (quartiles) of {rounds} requests per cell, one at a"
            " time on a keep-alive connection, the contenders taking turns in each round; every time"
            " includes the client's encoding (JPEG quality 95 where JPEG). Checked first: the raw regions'"
            " answer is the whole frame's byte for byte, and the peer's is the service's for the same JPEG.",
            "",
            "### Ratios (medians of the same run)",
            "",
            *ratios,
            "",
            "### Times",
            "",
            *rows,
        ]
    )


def main(argv: list[str] | None = None) -> None:
    args = parse_args(argv)
    sample = load_sample(DEFAULT_MODEL_DIR / "samples")
    padding = json.loads((DEFAULT_MODEL_DIR / "manifest.json").read_text())["crop"]["padding"]
    points = [make_point(sample, w, h, boxes) for w, h in args.sizes for boxes in BOXES]
    machine = this_machine().describe()
    logs = Path(tempfile.mkdtemp(prefix="bench-frames-"))
    with SERVICE.running(logs / "service.log") as service, PEER.running(logs / "peer.log") as peer:
        contenders = Contenders(service.url, peer.url, padding)
        try:
            times = measure(contenders, points, args.rounds)
        finally:
            contenders.close()
    load_after = ", ".join(f"{v:.2f}" for v in os.getloadavg())
    command = " ".join(["python -m benchmarks.bench_frames", *(sys.argv[1:] if argv is None else argv)])
    page.write_section(
        args.output, "bench_frames", render(command, machine, points, times, args.rounds, load_after)
    )
    log(f"wrote the bench_frames section of {args.output}")


if __name__ == "__main__":
    main()
