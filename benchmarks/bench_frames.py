"""A camera frame in memory to the parsed answer, one request at a time, side by side.

    python -m benchmarks.bench_frames              # 4 sizes x 1 and 4 boxes, 15 rounds; docs/performance.md
    python -m benchmarks.bench_frames --rounds 3 --sizes 640x480 --output /tmp/p.md   # a smoke run
    python -m benchmarks.bench_frames --gap-ms 0   # each request right after the previous one

Frames of 640x480, 1280x720, 1920x1080 and 3840x2160 (the samples folder's busiest image scaled
to the height, the rest of the width its mirror image), 1 and 4 boxes, concurrency 1, keep-alive
connections. Each round sends, in turn: the service with the boxes' regions as raw pixels and as
JPEG (POST /v1/predict/frame, the client's ``frame_parts``), the service's int8 variant (a second
service process, ``CKS_MODEL_DIR=models/lmo-synth-unet-int8``) with raw regions, the service with the
whole frame as JPEG (POST /v1/predict), the plain FastAPI peer (benchmarks/peers/fastapi_app.py,
the fastest peer at concurrency 1 in bench_peers) with the whole JPEG, and through the Python client
``predict(frame)`` against JPEG encode + ``predict(jpeg bytes)``. Every time includes the
client's encoding and the parsing of the answer. Before timing: each service's raw regions' answer
must be its whole frame's (PNG) byte for byte, and the peer's the service's for the same JPEG.
Issue 47's goal: at 1920x1080 with 4 boxes, the int8 raw regions at least 3x sooner than FastAPI's
whole JPEG.
Each request starts ``--gap-ms`` (50) after the previous one ended, as frames come from a camera:
longer than the peer's onnxruntime threads spin after its run (30-40 ms of CPU measured), so
that no request pays for another contender's. Writes the ``bench_frames`` section of
docs/performance.md.
"""

from __future__ import annotations

import argparse
import json
import random
import statistics
import sys
import tempfile
import time
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import cv2
import httpx
import numpy as np

from benchmarks.harness import (
    BOXES,
    PERFORMANCE_PAGE,
    ROOT,
    Sample,
    Server,
    load_average,
    load_sample,
    log,
    this_machine,
    write_section,
)
from benchmarks.peers.answers import difference
from benchmarks.peers.servers import PEERS, SERVICE, SERVICE_INT8
from service.infra.settings import DEFAULT_MODEL_DIR

sys.path.insert(0, str(ROOT / "client"))  # this checkout's client, not an installed copy

from keypoint_client import KeypointClient  # noqa: E402
from keypoint_client.frames import frame_parts, jpeg_bytes  # noqa: E402

SIZES = ((640, 480), (1280, 720), (1920, 1080), (3840, 2160))
PEER = next(peer for peer in PEERS if peer.name == "FastAPI")
CONTENDERS = (
    "service, raw regions",
    "service int8, raw regions",
    "service, JPEG regions",
    "service, whole JPEG",
    "FastAPI, whole JPEG",
    "client predict(frame)",
    "client JPEG + predict",
)
#: each (slower, faster) pair's ratio of medians and of mean CPU
RATIOS = (
    ("FastAPI, whole JPEG", "service, raw regions"),
    ("FastAPI, whole JPEG", "service int8, raw regions"),
    ("service, whole JPEG", "service, raw regions"),
    ("client JPEG + predict", "client predict(frame)"),
    ("service, whole JPEG", "FastAPI, whole JPEG"),
)
GOAL = ("1920x1080, 4 boxes", RATIOS[1], 3.0)  # issue 47: the int8 raw regions 3x sooner than FastAPI
Send = Callable[[], object]


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rounds", type=int, default=15, help="timed requests per contender and point")
    parser.add_argument(
        "--sizes", default=",".join(f"{w}x{h}" for w, h in SIZES), help="e.g. 640x480,1920x1080"
    )
    parser.add_argument("--output", type=Path, default=PERFORMANCE_PAGE)
    parser.add_argument("--seed", type=int, default=None, help="the turns' order (default: a fresh one)")
    parser.add_argument(
        "--gap-ms", type=float, default=50.0, help="idle time before each timed request (a camera's cadence)"
    )
    args = parser.parse_args(argv)
    args.seed = random.SystemRandom().randrange(2**31) if args.seed is None else args.seed
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

    def __init__(self, service: Server, int8: Server, peer: Server, padding: float) -> None:
        self.servers = service, int8, peer
        self.http = httpx.Client(base_url=service.url, timeout=120)
        self.int8 = httpx.Client(base_url=int8.url, timeout=120)
        self.peer = httpx.Client(base_url=peer.url, timeout=120)
        self.client = KeypointClient(service.url, timeout=120)
        self.padding = padding

    def close(self) -> None:
        for closable in (self.http, self.int8, self.peer, self.client):
            closable.close()

    def regions(self, point: Point, sending: str = "regions", http: httpx.Client | None = None) -> dict:
        files = frame_parts(point.frame, point.parameters, self.padding, sending)  # type: ignore[arg-type]
        return _answer((http or self.http).post("/v1/predict/frame", files=files))

    def whole_jpeg(self, point: Point, http: httpx.Client) -> dict:
        files = {"image": ("frame.jpg", jpeg_bytes(point.frame), "image/jpeg")}
        return _answer(http.post("/v1/predict", files=files, data={"request": json.dumps(point.parameters)}))

    def sends(self, point: Point) -> dict[str, tuple[Send, Server]]:
        """Each contender's request, and the server that answers it."""
        instances = point.parameters["instances"]
        service, int8, peer = self.servers
        sends = (
            (lambda: self.regions(point), service),
            (lambda: self.regions(point, http=self.int8), int8),
            (lambda: self.regions(point, "jpeg-regions"), service),
            (lambda: self.whole_jpeg(point, self.http), service),
            (lambda: self.whole_jpeg(point, self.peer), peer),
            (lambda: self.client.predict(point.frame, instances), service),
            (lambda: self.client.predict(jpeg_bytes(point.frame), instances), service),
        )
        return dict(zip(CONTENDERS, sends, strict=True))

    def check(self, point: Point) -> None:
        """Each service's raw regions answer as its whole frame's PNG does, byte for byte (the int8
        variant is another model: its answers are its own); the peer as the service."""
        png = cv2.imencode(".png", point.frame[:, :, ::-1])[1].tobytes()  # a raw 4K frame is above 20 MiB
        files = {"image": ("frame.png", png, "image/png")}
        for http, variant in ((self.http, "original"), (self.int8, "int8")):
            whole = http.post("/v1/predict", files=files, data={"request": json.dumps(point.parameters)})
            regions = frame_parts(point.frame, point.parameters, self.padding, "regions")
            answer = http.post("/v1/predict/frame", files=regions)
            if whole.status_code != 200 or answer.content != whole.content:
                raise SystemExit(f"{point.name}: the {variant} raw regions' answer is not the whole frame's")
            if answer.json()["model"]["variant"] != variant:
                raise SystemExit(f"{point.name}: {http.base_url} does not serve the {variant} model")
        why = difference(self.whole_jpeg(point, self.http), self.whole_jpeg(point, self.peer))
        if why is not None:
            raise SystemExit(f"{point.name}: the peer's answer differs from the service's: {why}")


def _answer(response: httpx.Response) -> dict:
    response.raise_for_status()
    return response.json()


@dataclass
class Timings:
    """Per (point, contender): wall milliseconds of each request, and the CPU milliseconds the
    client process and the answering server spent on them (their sum, for a mean per request)."""

    wall: dict[tuple[str, str], list[float]] = field(default_factory=dict)
    cpu: dict[tuple[str, str], float] = field(default_factory=dict)

    def add(self, key: tuple[str, str], wall_s: float, cpu_s: float) -> None:
        self.wall.setdefault(key, []).append(1000 * wall_s)
        self.cpu[key] = self.cpu.get(key, 0.0) + 1000 * cpu_s

    def median(self, key: tuple[str, str]) -> float:
        return statistics.median(self.wall[key])

    def cpu_mean(self, key: tuple[str, str]) -> float:
        return self.cpu[key] / len(self.wall[key])


def measure(contenders: Contenders, points: list[Point], rounds: int, seed: int, gap_s: float) -> Timings:
    """The contenders taking turns within each round (paired), in an order drawn afresh each round,
    each request ``gap_s`` after the previous one (a peer's onnxruntime threads spin for a while
    after its run, on the cores the next request needs); CPU read outside the timed span."""
    timings = Timings()
    order = random.Random(seed)
    for point in points:
        contenders.check(point)
        sends = contenders.sends(point)
        for send, _ in sends.values():  # warm: connections, first runs of each batch size
            send()
        for _ in range(rounds):
            for name, (send, server) in order.sample(list(sends.items()), len(sends)):
                time.sleep(gap_s)
                cpu_before = time.process_time() + server.cpu_seconds()
                started = time.perf_counter()
                send()
                wall = time.perf_counter() - started
                timings.add((point.name, name), wall, time.process_time() + server.cpu_seconds() - cpu_before)
        log(f"{point.name}: " + ", ".join(f"{n} {timings.median((point.name, n)):.1f}" for n in sends))
    return timings


def _cell(values: list[float]) -> str:
    quartiles = statistics.quantiles(values, n=4) if len(values) > 1 else [values[0]] * 3
    return f"{quartiles[1]:.1f} ({quartiles[0]:.1f}-{quartiles[2]:.1f})"


def _ratio(figure: Callable[[tuple[str, str]], float], point: str, slow: str, fast: str) -> float:
    return figure((point, slow)) / figure((point, fast))


def goal_line(points: list[Point], timings: Timings) -> str:
    """Issue 47's goal for the frame path, and whether this run met it."""
    name, (slow, fast), target = GOAL
    text = (
        f"Goal (issue 47): at {name.replace(',', ' with')}, the service int8 with raw regions at least"
        f" {target:g}x sooner than FastAPI with the whole JPEG (wall-time medians)"
    )
    if name not in {p.name for p in points}:
        return text + ": not measured in this run."
    ratio = _ratio(timings.median, name, slow, fast)
    return text + f": **{ratio:.2f}x**, {'met' if ratio >= target else '**NOT met**'}."


def render(
    command: str,
    machine: str,
    points: list[Point],
    timings: Timings,
    rounds: int,
    seed: int,
    gap_ms: float,
    load: str,
) -> str:
    header = "| frame, boxes | " + " | ".join(CONTENDERS) + " |"
    rule = "|" + "---|" * (len(CONTENDERS) + 1)
    walls = [header, rule]
    walls += [
        f"| {p.name} | " + " | ".join(_cell(timings.wall[p.name, n]) for n in CONTENDERS) + " |"
        for p in points
    ]
    cpus = [header, rule]
    cpus += [
        f"| {p.name} | " + " | ".join(f"{timings.cpu_mean((p.name, n)):.1f}" for n in CONTENDERS) + " |"
        for p in points
    ]
    labels = [f"{slow.replace(',', '')} / {fast.replace(',', '')}, time (CPU)" for slow, fast in RATIOS]
    ratios = ["| frame, boxes | " + " | ".join(labels) + " |", "|---" * (len(RATIOS) + 1) + "|"]
    for p in points:
        cells = [
            f"**{_ratio(timings.median, p.name, *pair):.2f}** ({_ratio(timings.cpu_mean, p.name, *pair):.2f})"
            for pair in RATIOS
        ]
        ratios.append(f"| {p.name} | " + " | ".join(cells) + " |")
    return "\n".join(
        [
            "## A camera frame to sets (bench_frames)",
            "",
            f"`{command}`: {machine}; load average after the run {load}. From a frame in memory (RGB) to"
            f" the parsed answer, {rounds} requests per cell, one at a time on a keep-alive connection, the"
            f" contenders taking turns in each round in an order drawn afresh (seed {seed}), each request"
            f" {gap_ms:g} ms after the previous one ended (as frames come from a camera; and the peer's"
            " onnxruntime threads spin for 30-40 ms of CPU after its run, which the next request would"
            " pay for); 4 boxes are"
            " the sample's 3 and its first again (as in"
            " bench_peers: the client's regions share one rectangle for those two); every figure includes"
            " the client's encoding (JPEG"
            " quality 95 where JPEG). CPU: the client process's and the answering server's CPU time per"
            " request (less moved by other jobs on the machine than the wall time). The service int8: a"
            " second service process serving the bundled int8 variant (`CKS_MODEL_DIR=models/"
            "lmo-synth-unet-int8`; another model, its sets differ a little). Checked first: each service's"
            " raw regions' answer is its whole frame's PNG's byte for byte, and the peer's is the (float32)"
            " service's for the same JPEG.",
            "",
            "### Ratios (wall-time medians, and mean CPU, of the same run)",
            "",
            *ratios,
            "",
            goal_line(points, timings),
            "",
            "### Wall time, ms: median (quartiles)",
            "",
            *walls,
            "",
            "### CPU time, core-ms per request (client + server), mean",
            "",
            *cpus,
        ]
    )


def main(argv: list[str] | None = None) -> None:
    args = parse_args(argv)
    sample = load_sample()
    padding = json.loads((DEFAULT_MODEL_DIR / "manifest.json").read_text())["crop"]["padding"]
    points = [make_point(sample, w, h, boxes) for w, h in args.sizes for boxes in BOXES]
    machine = this_machine().describe()
    logs = Path(tempfile.mkdtemp(prefix="bench-frames-"))
    with (
        SERVICE.running(logs / "service.log") as service,
        SERVICE_INT8.running(logs / "service-int8.log") as int8,
        PEER.running(logs / "peer.log") as peer,
    ):
        contenders = Contenders(service, int8, peer, padding)
        try:
            timings = measure(contenders, points, args.rounds, args.seed, args.gap_ms / 1000)
        finally:
            contenders.close()
    command = " ".join(["python -m benchmarks.bench_frames", *(sys.argv[1:] if argv is None else argv)])
    text = render(command, machine, points, timings, args.rounds, args.seed, args.gap_ms, load_average())
    write_section(args.output, "bench_frames", text)
    log(f"wrote the bench_frames section of {args.output}")


if __name__ == "__main__":
    main()
