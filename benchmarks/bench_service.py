"""The service against its bare model: throughput and latency beside raw onnxruntime, where one
request's time goes, and the server's memory under load.

    python -m benchmarks.bench_service            # ~6 min; writes its section of docs/performance.md
    python -m benchmarks.bench_service --quick    # a few seconds per point, for development

Needs wrk (``apt-get install -y wrk``). The model is ``CKS_MODEL_DIR`` (default: the bundled
model) and its ``samples/`` COCO folder; other ``CKS_*`` variables set the headline settings.
Raw = the bare ``onnxruntime.InferenceSession`` built by ``service.detector.session.create_session``
in fresh processes laid out as the server's (``CKS_WORKERS`` processes, ``CKS_INFERENCE_THREADS``
intra-op threads), driven by <concurrency> threads on the request's crops.
"""

from __future__ import annotations

import argparse
import multiprocessing
import os
import sys
import tempfile
import threading
import time
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from benchmarks.harness import (
    BOXES,
    PERFORMANCE_PAGE,
    LoadResult,
    Machine,
    Requests,
    Sample,
    load_sample,
    log,
    require_wrk,
    run_wrk,
    serve,
    this_machine,
    write_section,
)
from benchmarks.stages import STAGES, service_state, stage_breakdown
from service.detector.images import decode_image
from service.detector.manifest import MODEL_FILENAME, load_manifest
from service.detector.preprocess import build_batch
from service.detector.session import create_session, file_sha256
from service.infra.settings import DEFAULT_MODEL_DIR, Settings

CONCURRENCIES = (1, 4, 16)
SETTING_NAMES = ("workers", "inference_threads", "max_concurrent_inferences")
RATIO_GOAL, MEMORY_GOAL = 0.85, 0.05
STAGE_LABELS = {
    "decode": "decode (`decode_image`)",
    "crop": "crop + normalize (`build_batch`)",
    "inference": "inference (`Detector.run`)",
    "sets": "scoring / sets (`calibrated_sets`)",
    "response": "rest of predict (`Predictor.predict`)",
    "json": "response body (`predict_json`)",
}


@dataclass(frozen=True)
class Plan:
    seconds: float  # per point
    warmup_seconds: float
    memory_seconds: tuple[float, ...]  # wrk runs at concurrency 16, VmRSS read after each
    iterations: int  # of the in-process breakdown


QUICK, FULL = Plan(2.0, 1.0, (2.0, 6.0), 10), Plan(10.0, 2.0, (10.0, 90.0), 100)


# ---------------------------------------------------------------- raw onnxruntime


@dataclass(frozen=True)
class RawResult:
    runs_per_s: float
    p50_ms: float


def _drive(model_dir: str, threads: int, batch: np.ndarray, concurrency: int, seconds: float) -> list[float]:
    """One process: ``concurrency`` threads running the batch back to back for ``seconds``."""
    manifest = load_manifest(Path(model_dir))
    session = create_session(Path(model_dir) / MODEL_FILENAME, threads)
    feed, outputs = {manifest.input.name: batch}, [manifest.output.name]
    session.run(outputs, feed)  # warm-up
    latencies: list[list[float]] = [[] for _ in range(concurrency)]
    deadline = time.perf_counter() + seconds

    def loop(mine: list[float]) -> None:
        while (start := time.perf_counter()) < deadline:
            session.run(outputs, feed)
            mine.append(time.perf_counter() - start)

    workers = [threading.Thread(target=loop, args=(mine,)) for mine in latencies]
    for worker in workers:
        worker.start()
    for worker in workers:
        worker.join()
    return [value for mine in latencies for value in mine]


def raw_session(
    model_dir: Path, threads: int, batch: np.ndarray, concurrency: int, seconds: float, processes: int = 1
) -> RawResult:
    """Runs/s of ``concurrency`` callers spread over ``processes`` fresh processes (so that this
    one's state shares none of their CPU)."""
    shares = [concurrency // processes + (i < concurrency % processes) for i in range(processes)]
    jobs = [(str(model_dir), threads, batch, n, seconds) for n in shares if n]
    with multiprocessing.get_context("spawn").Pool(len(jobs)) as pool:
        latencies = [value for part in pool.starmap(_drive, jobs) for value in part]
    return RawResult(len(latencies) / seconds, float(np.percentile(latencies, 50)) * 1e3)


# ---------------------------------------------------------------- the run


@dataclass
class Point:
    """One (instances, concurrency) point: the service and the raw session side by side."""

    instances: int
    concurrency: int
    service: LoadResult
    raw: RawResult
    load_1m: float = field(default_factory=lambda: os.getloadavg()[0])  # after the point

    @property
    def ratio(self) -> float:
        return self.service.requests_per_s / self.raw.runs_per_s


@dataclass
class Results:
    command: str
    machine: Machine
    load_at_end: tuple[float, float, float]
    model: str
    settings: dict[str, int]
    points: list[Point]
    memory: list[tuple[int, int]]  # (requests so far, VmRSS KiB)
    breakdown: dict[int, dict[str, float]]  # instances -> stage -> median ms

    def point(self, instances: int, concurrency: int) -> Point:
        return next(p for p in self.points if (p.instances, p.concurrency) == (instances, concurrency))

    @property
    def growth(self) -> float:
        return self.memory[-1][1] / self.memory[0][1] - 1


def format_point(point: Point) -> str:
    s = point.service
    return (
        f"{point.instances} inst c={point.concurrency:<2}  service {s.requests_per_s:7.1f} req/s "
        f"p50 {s.p50_ms:7.1f} ms p99 {s.p99_ms:7.1f} ms  raw {point.raw.runs_per_s:7.1f}/s  "
        f"ratio {point.ratio:.2f}  errors {s.errors}  load {point.load_1m:.1f}"
    )


def measure(
    plan: Plan, model_dir: Path, sample: Sample, settings: dict[str, int], directory: Path
) -> tuple[list[Point], list[tuple[int, int]]]:
    """Memory first (VmRSS after each run of 1-instance requests), then every point, service then raw."""
    requests = Requests.write(directory, sample)
    manifest, image = load_manifest(model_dir), decode_image(sample.jpeg, 10**9)
    batches = {n: build_batch(image, sample.with_instances(n).boxes, manifest)[0] for n in BOXES}
    env = {"CKS_MODEL_DIR": str(model_dir), **{f"CKS_{k.upper()}": str(v) for k, v in settings.items()}}
    points, memory, served = [], [], 0
    with serve(env, log=directory / "server.log") as server:
        for boxes in BOXES:
            run_wrk(server.url, requests.scripts[boxes], 4, plan.warmup_seconds)
        for seconds in plan.memory_seconds:
            served += run_wrk(server.url, requests.scripts[1], 16, seconds).requests
            memory.append((served, server.rss_kib()))
            log(f"memory: {served} requests, VmRSS {memory[-1][1] / 1024:.1f} MiB")
        for boxes in BOXES:
            for concurrency in CONCURRENCIES:
                service = run_wrk(server.url, requests.scripts[boxes], concurrency, plan.seconds)
                threads, processes = settings["inference_threads"], settings["workers"]
                raw = raw_session(model_dir, threads, batches[boxes], concurrency, plan.seconds, processes)
                points.append(Point(boxes, concurrency, service, raw))
                log(format_point(points[-1]))
    return points, memory


def model_description(model_dir: Path) -> str:
    manifest = load_manifest(model_dir)
    spec, digest = manifest.input, file_sha256(model_dir / MODEL_FILENAME)[:12]
    bundled = model_dir == DEFAULT_MODEL_DIR.resolve()
    return (
        f"`{manifest.name}` from `{model_dir}` (model.onnx sha256 {digest}...), input "
        f"{spec.height}x{spec.width}, {manifest.num_keypoints} keypoints, heatmaps "
        f"{manifest.output.height}x{manifest.output.width}"
        + ("" if bundled else " (**not** the bundled model: CKS_MODEL_DIR points elsewhere)")
    )


def run(quick: bool) -> Results:
    machine = this_machine()
    log(f"machine: {machine.describe()}")
    model_dir = Path(Settings().model.directory).resolve()
    sample = load_sample(model_dir / "samples")
    settings = {name: Settings().value(name) for name in SETTING_NAMES}
    plan = QUICK if quick else FULL
    with tempfile.TemporaryDirectory(prefix="cks-bench-") as directory:
        points, memory = measure(plan, model_dir, sample, settings, Path(directory))
    with service_state(model_dir, settings["inference_threads"]) as state:
        stages = {n: stage_breakdown(state, sample.with_instances(n), plan.iterations) for n in BOXES}
    return Results(
        command="python -m benchmarks.bench_service" + (" --quick" if quick else ""),
        machine=machine,
        load_at_end=os.getloadavg(),
        model=model_description(model_dir),
        settings=settings,
        points=points,
        memory=memory,
        breakdown=stages,
    )


# ---------------------------------------------------------------- the section


def _ok(met: bool) -> str:
    return "yes" if met else "**no**"


def goals(r: Results) -> list[str]:
    lines = ["| goal | measured | met |", "|---|---|---|"]
    for count in BOXES:
        ratio = r.point(count, 16).ratio
        lines.append(
            f"| service / raw throughput at concurrency 16, {count} instance(s) >= {RATIO_GOAL} "
            f"| {ratio:.2f} | {_ok(ratio >= RATIO_GOAL)} |"
        )
    (first, _), (last, _) = r.memory[0], r.memory[-1]
    lines.append(
        f"| RSS after {last} requests within {MEMORY_GOAL:.0%} of after {first} "
        f"| {r.growth:+.1%} | {_ok(abs(r.growth) <= MEMORY_GOAL)} |"
    )
    return lines


def throughput(r: Results) -> list[str]:
    lines = [
        "| instances | concurrency | service req/s | p50 ms | p99 ms | raw req/s | raw p50 ms | service/raw "
        "| errors | wrk CPU | load 1m |",
        "|---|---|---|---|---|---|---|---|---|---|---|",
    ]
    for p in r.points:
        s = p.service
        lines.append(
            f"| {p.instances} | {p.concurrency} | {s.requests_per_s:.1f} | {s.p50_ms:.1f} | {s.p99_ms:.1f} "
            f"| {p.raw.runs_per_s:.1f} | {p.raw.p50_ms:.1f} | **{p.ratio:.2f}** | {s.errors} "
            f"| {s.loadgen_cpu_share:.0%} | {p.load_1m:.1f} |"
        )
    return lines


def breakdown(r: Results) -> list[str]:
    head = " | ".join(f"{c} instance(s) ms | share" for c in BOXES)
    lines = [f"| stage | {head} |", "|---|" + "---|---|" * len(BOXES)]
    latency = {c: r.point(c, 1).service.p50_ms for c in BOXES}
    framework = {c: max(0.0, latency[c] - r.breakdown[c]["total"]) for c in BOXES}
    for stage in STAGES:
        cells = " | ".join(
            f"{r.breakdown[c][stage]:.2f} | {r.breakdown[c][stage] / latency[c]:.0%}" for c in BOXES
        )
        lines.append(f"| {STAGE_LABELS[stage]} | {cells} |")
    cells = " | ".join(f"{framework[c]:.2f} | {framework[c] / latency[c]:.0%}" for c in BOXES)
    lines.append(f"| HTTP / framework / queueing (p50 at c=1 minus the above) | {cells} |")
    cells = " | ".join(f"{latency[c]:.2f} | 100% " for c in BOXES)
    lines.append(f"| **service p50 latency at concurrency 1** | {cells} |")
    return lines


def ceiling(r: Results) -> list[str]:
    """What the breakdown and the core-ms per request imply for the service/raw goal."""
    lines = []
    for count in BOXES:
        stages, point = r.breakdown[count], r.point(count, 16)
        total = max(stages["total"], r.point(count, 1).service.p50_ms)
        service_ms = r.machine.cpus * 1e3 / point.service.requests_per_s
        raw_ms = r.machine.cpus * 1e3 / point.raw.runs_per_s
        extra = service_ms - raw_ms
        lines.append(
            f"- {count} instance(s): inference is {stages['inference']:.1f} ms of {total:.1f} ms per request "
            f"(p50 at concurrency 1), so with every stage CPU-bound on the same cores the service can reach "
            f"about **{stages['inference'] / total:.2f}** of the raw throughput. At concurrency 16, "
            f"{service_ms:.1f} core-ms per request in the service vs {raw_ms:.1f} in the raw session "
            f"(cores / throughput): {extra:.1f} besides the model, so a ratio of {RATIO_GOAL} needs a "
            f"model of at least {extra * RATIO_GOAL / (1 - RATIO_GOAL):.0f} core-ms per request; with JPEG "
            f"decoding ({stages['decode']:.1f} ms) as the only extra work, this model would reach "
            f"{raw_ms / (raw_ms + stages['decode']):.2f}."
        )
    return lines


def render(r: Results) -> str:
    load_end = ", ".join(f"{v:.2f}" for v in r.load_at_end)
    peak_load = max([r.machine.load_at_start[0], r.load_at_end[0], *(p.load_1m for p in r.points)])
    noisy = "- **The load average reached 1.5 or more: absolute figures are noisy; ratios are more robust.**"
    memory = [f"| {n} | {kib / 1024:.1f} |" for n, kib in r.memory]
    return "\n".join(
        [
            "## The service against its bare model (bench_service)",
            "",
            f"Generated by `{r.command}`; every figure below comes from that one run, service and baseline "
            "measured back to back.",
            "",
            f"- Machine: {r.machine.describe()}; load average at end {load_end}; highest 1-min load "
            f"average after a measured point {peak_load:.1f} (the benchmark's own server, wrk and baseline "
            "included).",
            *([noisy] if peak_load >= 1.5 else []),
            f"- Model: {r.model}.",
            "- Headline settings: "
            + ", ".join(f"`CKS_{k.upper()}={v}`" for k, v in r.settings.items())
            + " (the `CKS_*` environment of the command, else the service defaults).",
            "- Request: `POST /v1/predict`, multipart/form-data, one 640x480 JPEG of the model's `samples/` "
            "folder with 1 or 4 boxes, default options (`cov`, epsilon 0.1, keypoint coverage).",
            "- Load generator: `wrk -t1 -c<concurrency> --latency` on loopback (closed loop, keep-alive); "
            "its CPU use is the `wrk CPU` column (share of one core).",
            "",
            "### Goals",
            "",
            *goals(r),
            "",
            "### Service vs raw onnxruntime",
            "",
            "Raw = the bare session of `service.detector.session.create_session` in the server's process "
            "layout (`CKS_WORKERS` processes, `CKS_INFERENCE_THREADS` intra-op threads), on the request's "
            "crops, one `session.run` per request, driven by <concurrency> threads: no HTTP, decoding, "
            "cropping, scoring or JSON.",
            "",
            *throughput(r),
            "",
            "### Where the time goes (one request, in-process)",
            "",
            "Medians of single-threaded calls of the functions the route calls (`benchmarks/stages.py`); the "
            "last stage is the service's p50 at concurrency 1 minus their sum: multipart parsing, "
            "validation, the event loop, thread hand-offs and the socket.",
            "",
            *breakdown(r),
            "",
            *ceiling(r),
            "",
            "### Memory",
            "",
            "VmRSS of the server's processes, summed, after runs of 1-instance requests at concurrency 16:",
            "",
            "| requests served | VmRSS MiB |",
            "|---|---|",
            *memory,
            "",
        ]
    )


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--quick", action="store_true", help="a few seconds per point")
    parser.add_argument(
        "--output", type=Path, default=PERFORMANCE_PAGE, help="the page to write its section in"
    )
    args = parser.parse_args(argv)
    require_wrk()
    started = time.monotonic()
    text = render(run(args.quick))
    write_section(args.output, "bench_service", text)
    log(f"\n{text}\nwrote {args.output} in {time.monotonic() - started:.0f} s")
    return 0


if __name__ == "__main__":
    sys.exit(main())
