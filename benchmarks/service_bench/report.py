"""docs/performance.md from one run's measurements (and the same figures for stdout)."""

from __future__ import annotations

from dataclasses import dataclass

from benchmarks.service_bench.breakdown import STAGES
from benchmarks.service_bench.machine import Machine
from benchmarks.service_bench.offline import Calibration, PostProcessing
from benchmarks.service_bench.runs import BATCHED_CROPS, Memory, Point, Variant
from service.conformal.kernel import native_kernel_available

RATIO_GOAL, SPEEDUP_GOAL, MEMORY_GOAL = 0.85, 20.0, 0.05
NOISE = 0.10  # throughput changes smaller than this are not called an effect
STAGE_LABELS = {
    "decode": "decode (`decode_image`)",
    "crop": "crop + normalize (`build_batch`)",
    "inference": "inference (`Detector.run`)",
    "sets": "scoring / sets (`calibrated_sets`)",
    "response": "rest of predict (`Predictor.predict`)",
    "json": "response body (`predict_json`)",
}


@dataclass
class Results:
    command: str
    quick: bool
    machine: Machine
    load_at_end: tuple[float, float, float]
    model: str
    settings: dict[str, int]
    points: list[Point]
    memory: Memory | None
    extra: dict
    breakdown: dict[int, dict[str, float]]
    post: list[PostProcessing]
    calibration: Calibration
    tuning: list[Variant]

    def point(self, instances: int, concurrency: int) -> Point:
        return next(p for p in self.points if (p.instances, p.concurrency) == (instances, concurrency))


def _ok(met: bool) -> str:
    return "yes" if met else "**no**"


def summary(r: Results) -> list[str]:
    lines = ["| goal | measured | met |", "|---|---|---|"]
    for count in (1, 4):
        ratio = r.point(count, 16).ratio
        lines.append(
            f"| service / raw throughput at concurrency 16, {count} instance(s) >= {RATIO_GOAL} "
            f"| {ratio:.2f} | {_ok(ratio >= RATIO_GOAL)} |"
        )
    worst = min(r.post, key=lambda p: p.speedup)
    lines.append(
        f"| post-processing vs per-heatmap loop >= {SPEEDUP_GOAL:.0f}x (slowest function) "
        f"| {worst.speedup:.1f}x ({worst.kind}) | {_ok(worst.speedup >= SPEEDUP_GOAL)} |"
    )
    if r.memory:
        (n0, _), (n1, _) = r.memory.after[0], r.memory.after[-1]
        lines.append(
            f"| RSS after {n1} requests within {MEMORY_GOAL:.0%} of after {n0} "
            f"| {r.memory.growth:+.1%} | {_ok(abs(r.memory.growth) <= MEMORY_GOAL)} |"
        )
    c = r.calibration
    lines.append(f"| calibration scoring (no goal) | {c.instances_per_s:.0f} instances/s | - |")
    lines.append(
        f"| write a version of {c.store_instances} instances, SQLite (no goal) "
        f"| {c.store_write_best_s:.2f} s | - |"
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
            f"| {p.raw_requests_per_s:.1f} | {p.raw.p50_ms:.1f} | **{p.ratio:.2f}** | {s.errors} "
            f"| {s.loadgen_cpu_share:.0%} | {p.load_1m:.1f} |"
        )
    return lines


def breakdown(r: Results) -> list[str]:
    counts = sorted(r.breakdown)
    head = " | ".join(f"{c} instance(s) ms | share" for c in counts)
    lines = [f"| stage | {head} |", "|---|" + "---|---|" * len(counts)]
    latency = {c: r.point(c, 1).service.p50_ms for c in counts}
    framework = {c: max(0.0, latency[c] - r.breakdown[c]["total"]) for c in counts}
    for stage in STAGES:
        cells = " | ".join(
            f"{r.breakdown[c][stage]:.2f} | {r.breakdown[c][stage] / latency[c]:.0%}" for c in counts
        )
        lines.append(f"| {STAGE_LABELS[stage]} | {cells} |")
    cells = " | ".join(f"{framework[c]:.2f} | {framework[c] / latency[c]:.0%}" for c in counts)
    lines.append(f"| HTTP / framework / queueing (p50 at c=1 minus the above) | {cells} |")
    cells = " | ".join(f"{latency[c]:.2f} | 100% " for c in counts)
    lines.append(f"| **service p50 latency at concurrency 1** | {cells} |")
    return lines


def post_processing(r: Results) -> list[str]:
    lines = [
        "| function | per-heatmap loop us/heatmap | vectorized us/heatmap | speed-up |",
        "|---|---|---|---|",
    ]
    for p in r.post:
        lines.append(f"| {p.kind} | {p.loop_us:.1f} | {p.vectorized_us:.1f} | **{p.speedup:.1f}x** |")
    return lines


def memory(r: Results) -> list[str]:
    if not r.memory:
        return ["(skipped: --skip-memory)"]
    lines = ["| requests served | VmRSS MiB |", "|---|---|"]
    lines += [f"| {n} | {kib / 1024:.1f} |" for n, kib in r.memory.after]
    lines += [
        "",
        f"Growth between the two readings: {r.memory.growth:+.1%} (goal: within {MEMORY_GOAL:.0%}).",
    ]
    return lines


def _tuning_rows(r: Results) -> list[tuple[str, list[Point]]]:
    rows = [("headline settings", [r.point(1, 16), r.point(4, 16)])]
    return rows + [(v.label, v.points) for v in r.tuning]


def tuning(r: Results) -> list[str]:
    lines = [
        "| settings (change from the headline) | 1 inst req/s | vs headline | p99 ms | service/raw "
        "| 4 inst req/s | vs headline | p99 ms | service/raw | load 1m |",
        "|---|---|---|---|---|---|---|---|---|---|",
    ]
    base = [r.point(1, 16).service.requests_per_s, r.point(4, 16).service.requests_per_s]
    for label, points in _tuning_rows(r):
        cells = [
            f"{p.service.requests_per_s:.1f} | {p.service.requests_per_s / b - 1:+.0%} "
            f"| {p.service.p99_ms:.0f} | {p.ratio:.2f}"
            for p, b in zip(points, base, strict=True)
        ]
        lines.append(f"| {label} | {' | '.join(cells)} | {points[-1].load_1m:.1f} |")
    return lines


def ceiling(r: Results) -> list[str]:
    """What the breakdown implies for service/raw when every stage competes for the same cores."""
    lines = []
    for count, stages in sorted(r.breakdown.items()):
        total = stages["total"] + max(0.0, r.point(count, 1).service.p50_ms - stages["total"])
        lines.append(
            f"- {count} instance(s): inference is {stages['inference']:.1f} ms of {total:.1f} ms per request "
            f"(p50 at concurrency 1), so with every stage CPU-bound on the same cores the service can "
            f"reach about **{stages['inference'] / total:.2f}** of the raw per-request throughput."
        )
    lines.extend(overhead_bound(r))
    unbatched = r.point(1, 1).raw.runs_per_s
    batched = r.extra["batched-1"].runs_per_s * BATCHED_CROPS
    lines.append(
        f"- Batching gain of the model itself: {batched:.0f} crops/s in batches of {BATCHED_CROPS} vs "
        f"{unbatched:.0f} crops/s one crop per run (one caller): x{batched / unbatched:.2f}."
    )
    return lines


def overhead_bound(r: Results, goal: float = RATIO_GOAL) -> list[str]:
    """The model cost at which the measured per-request overhead would meet the ratio goal.

    Core-ms per request = cores * 1000 / (req/s) at concurrency 16, on both sides: the raw
    session keeps every core busy, so its figure is the model's cost; the service's extra
    is the work the model does not share (decode, HTTP, crop, scoring, JSON) plus any time
    its cores wait. The ratio raw / (raw + extra) reaches ``goal`` once the model costs
    extra * goal / (1 - goal) per request.
    """
    lines = []
    for count in (1, 4):
        point = r.point(count, 16)
        service_ms = r.machine.cpus * 1e3 / point.service.requests_per_s
        raw_ms = r.machine.cpus * 1e3 / point.raw.runs_per_s
        extra = service_ms - raw_ms
        decode = r.breakdown[count]["decode"]
        lines.append(
            f"- {count} instance(s) at concurrency 16: {service_ms:.1f} core-ms per request in the service "
            f"vs {raw_ms:.1f} in the raw session (cores / throughput), so {extra:.1f} core-ms per request "
            f"besides the model. A ratio of {goal} needs a model of at least "
            f"{extra * goal / (1 - goal):.0f} core-ms per request "
            f"(this one: {raw_ms:.1f}); with JPEG decoding ({decode:.1f} ms) as the only extra work, "
            f"this model would reach {raw_ms / (raw_ms + decode):.2f}."
        )
    return lines


def best_variant(r: Results) -> tuple[str, float]:
    """The tuning row with the highest mean throughput gain over the headline at c=16."""
    base = [r.point(1, 16).service.requests_per_s, r.point(4, 16).service.requests_per_s]
    best, gain = "headline settings", 0.0
    for v in r.tuning:
        mean_gain = sum(p.service.requests_per_s / b - 1 for p, b in zip(v.points, base, strict=True)) / 2
        if mean_gain > gain:
            best, gain = v.label, mean_gain
    return best, gain


def _settings_text(settings: dict[str, int]) -> str:
    return ", ".join(f"`CKS_{k.upper()}={v}`" for k, v in settings.items())


def render(r: Results) -> str:
    """The whole of docs/performance.md."""
    load_end = ", ".join(f"{v:.2f}" for v in r.load_at_end)
    best, gain = best_variant(r)
    mode = "quick mode, a few seconds per point: development figures only" if r.quick else "full run"
    loads = [p.load_1m for p in r.points] + [p.load_1m for v in r.tuning for p in v.points]
    peak_load = max([r.machine.load_at_start[0], r.load_at_end[0], *loads])
    noisy = peak_load >= 1.5
    parts = [
        "# Performance",
        "",
        f"Generated by `{r.command}` ({mode}); every figure below comes from that one run, "
        "service and baseline measured back to back. Do not edit by hand.",
        "",
        f"- Machine: {r.machine.describe()}; load average at end {load_end}; highest 1-min load "
        f"average after a measured point {peak_load:.1f} (this includes the benchmark's own server, "
        "wrk and baseline threads; the `load 1m` columns give it per point).",
        *(
            [
                "- **The load average reached 1.5 or more during this run: if other jobs shared the CPU "
                "(the load at start says whether the machine was quiet), absolute figures are noisy and "
                "low; ratios measured back to back are more robust.**"
            ]
            if noisy
            else []
        ),
        f"- Model: {r.model}.",
        f"- Headline settings: {_settings_text(r.settings)} (the `CKS_*` environment of the command, "
        "else the service defaults).",
        "- Request: `POST /v1/predict`, multipart/form-data, one 640x480 JPEG of the model's `samples/` "
        "folder with 1 or 4 boxes, default options (`cov`, epsilon 0.1, keypoint coverage), JSON response.",
        "- Load generator: `wrk -t1 -c<concurrency> --latency` on loopback (closed loop, keep-alive), "
        "posting a prebuilt body from a Lua script; its CPU use is the `wrk CPU` column (share of one core).",
        "",
        "## Goals (ratios first)",
        "",
        *summary(r),
        "",
        "## Service vs raw onnxruntime",
        "",
        "Raw = the bare `onnxruntime.InferenceSession` built by the service's own "
        "`service.detector.session.create_session`, in the same process layout (`CKS_WORKERS` processes, "
        "`CKS_INFERENCE_THREADS` intra-op threads per run), on the same "
        "crops (the 1 or 4 crops of the request, one `session.run` per request-equivalent), driven by "
        "<concurrency> threads. No HTTP, decoding, cropping, scoring or JSON.",
        "",
        *throughput(r),
        "",
        f"JSON body (base64 image) instead of multipart, concurrency 16: "
        f"{r.extra['json-1'].requests_per_s:.1f} req/s (1 instance), "
        f"{r.extra['json-4'].requests_per_s:.1f} req/s (4 instances).",
        "",
        "## Where the time goes (one request, in-process)",
        "",
        "Median of repeated single-threaded calls of the functions the route calls "
        "(`rest of predict` = `predict()` with the inference and `calibrated_sets` results cached). "
        "The last stage is the service's p50 at concurrency 1 minus the in-process sum: "
        "multipart parsing, pydantic validation, the event loop, thread-pool hand-offs and the socket.",
        "",
        *breakdown(r),
        "",
        "What this means for the service/raw goal:",
        "",
        *ceiling(r),
        "",
        "## Post-processing per heatmap",
        "",
        "`benchmarks/bench_conformal.py`'s batch (76 heatmaps 64x64, top-K 100, anchor normalization): the "
        "vectorized nonconformity scores of `service.conformal` vs the straightforward per-heatmap loop "
        "(the authors' reference formulation), float32 heatmaps as the detector outputs.",
        "",
        *post_processing(r),
        "",
        "`peak` does little per heatmap besides the anchor normalization's exact median, which both "
        "sides pay: the loop with np.median, the service with the native kernel of "
        f"`service/conformal/kernel.py` ({'built' if native_kernel_available() else 'NOT built'}).",
        "",
        "## Calibration",
        "",
        f"- Scoring (`service.calibration.scoring.score_batch` on the samples COCO folder, decode + crop + "
        f"inference + three scores): {r.calibration.instances} instances in {r.calibration.seconds:.2f} s = "
        f"**{r.calibration.instances_per_s:.0f} instances/s**.",
        f"- Writing a version of {r.calibration.store_instances} instances to SQLite "
        f"(`benchmarks/bench_store.py`): best {r.calibration.store_write_best_s:.2f} s, median "
        f"{r.calibration.store_write_median_s:.2f} s.",
        "",
        "## Memory",
        "",
        "VmRSS of the server: the `serve` process and its worker processes, summed (`/proc/<pid>/status`), "
        "1-instance requests at concurrency 16:",
        "",
        *memory(r),
        "",
        "## Tuning",
        "",
        "Each row restarts the server with one change from the headline settings and measures concurrency 16 "
        "(raw baseline in that row's process layout).",
        "",
        *tuning(r),
        "",
        f"Best measured change at concurrency 16: **{best}**"
        + (f" (+{gain:.0%} mean throughput over the headline)." if gain > 0 else "."),
        "",
        *recommendations(r),
        "",
    ]
    return "\n".join(parts)


def _verdict(gains: list[float]) -> str:
    if all(g > NOISE for g in gains):
        return "**faster**"
    if all(g < -NOISE for g in gains):
        return "slower"
    return f"no clear effect (within +-{NOISE:.0%} on at least one request size)"


def recommendations(r: Results) -> list[str]:
    """Every tried change, classified by its measured effect at concurrency 16."""
    base = [r.point(1, 16).service.requests_per_s, r.point(4, 16).service.requests_per_s]
    lines = ["What was tried, and its effect on throughput at concurrency 16 (1 / 4 instances):", ""]

    def gains(v: Variant) -> list[float]:
        return [p.service.requests_per_s / b - 1 for p, b in zip(v.points, base, strict=True)]

    for v in sorted(r.tuning, key=lambda v: -sum(gains(v))):
        one, four = gains(v)
        lines.append(f"- {v.label}: {one:+.0%} / {four:+.0%}: {_verdict([one, four])}.")
    return lines
