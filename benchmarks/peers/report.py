"""The peer section of docs/performance.md (and stdout): goals first, then the table and settings."""

from __future__ import annotations

from collections.abc import Callable
from dataclasses import dataclass

from benchmarks.harness import BOXES, Machine
from benchmarks.peers.accelerator import execution_providers, gpu_names, on_gpu
from benchmarks.peers.answers import GPU_TOLERANCE, TOLERANCE
from benchmarks.peers.measure import CONCURRENCIES, Point, Runs
from benchmarks.peers.profile import Profile
from benchmarks.peers.servers import SERVICE_INT8, Contender
from benchmarks.stages import Limit, cores

SERVICE = "service"
INT8 = SERVICE_INT8.name
FASTAPI = "FastAPI"
STAGE_NAMES = {
    "decode": "decode",
    "crop": "crop",
    "inference": "inference",
    "sets": "sets",
    "response": "response data",
    "json": "JSON",
}


@dataclass(frozen=True)
class Goal:
    text: str
    measured: float
    target: float
    higher_is_better: bool
    detail: str

    @property
    def met(self) -> bool:
        return self.measured >= self.target if self.higher_is_better else self.measured <= self.target

    def row(self) -> str:
        verdict = "met" if self.met else "**NOT met**"
        return f"| {self.text} | {self.measured:.2f} ({self.detail}) | {self.target:.2f} | {verdict} |"


@dataclass(frozen=True)
class PeerResults:
    command: str
    machine: Machine
    load_at_end: tuple[float, float, float]
    seconds: float
    rounds: int
    contenders: list[Contender]
    runs: Runs
    limits: list[Limit]
    minutes: float
    profile: Profile | None = None

    @property
    def peers(self) -> list[str]:
        return [c.name for c in self.contenders if c.is_peer]

    @property
    def services(self) -> list[str]:
        """The service's contenders with a ratio column: the default, then the int8 variant if run."""
        return [c.name for c in self.contenders if not c.is_peer]

    def best_peer(self, point: tuple[int, int], by_rate: bool) -> str:
        if by_rate:
            return max(self.peers, key=lambda name: self.runs.rate(name, point))
        return min(self.peers, key=lambda name: self.runs.p50(name, point))


def goals(results: PeerResults) -> list[Goal]:
    runs, found = results.runs, []
    for boxes, latency_goal, rate_goal in ((1, 1.2, 1.2), (4, 1.1, 1.1)):
        point = (boxes, 1)
        best = results.best_peer(point, by_rate=False)
        found.append(
            Goal(
                f"p50 at concurrency 1, {boxes} box(es): service / best peer",
                runs.p50(SERVICE, point) / runs.p50(best, point),
                1 / latency_goal,
                False,
                f"{runs.p50(SERVICE, point):.1f} vs {runs.p50(best, point):.1f} ms, {best}",
            )
        )
        found.append(rate_against_best_peer(results, SERVICE, boxes, rate_goal))
    found += int8_goals(results) if INT8 in results.services and results.peers else []
    for limit in results.limits:
        rate = runs.rate(SERVICE, (limit.boxes, 16))
        found.append(
            Goal(
                f"req/s at concurrency 16, {limit.boxes} box(es): service / in-process limit",
                rate / limit.requests_per_s,
                0.85,
                True,
                f"{rate:.0f} vs {cores()} cores / {limit.core_ms:.2f} core-ms = {limit.requests_per_s:.0f}",
            )
        )
        p50 = runs.p50(SERVICE, (limit.boxes, 1))
        found.append(
            Goal(
                f"p50 at concurrency 1, {limit.boxes} box(es): service / in-process latency",
                p50 / limit.best_latency_ms,
                1.15,
                False,
                f"{p50:.1f} vs {limit.best_latency_ms:.1f} ms with {limit.best_threads} intra-op thread(s)",
            )
        )
    return found


def rate_against_best_peer(results: PeerResults, name: str, boxes: int, target: float) -> Goal:
    """req/s at concurrency 16: ``name`` against the fastest peer at that point."""
    runs, point = results.runs, (boxes, 16)
    best = results.best_peer(point, by_rate=True)
    return Goal(
        f"req/s at concurrency 16, {boxes} box(es): {name} / best peer",
        runs.rate(name, point) / runs.rate(best, point),
        target,
        True,
        f"{runs.rate(name, point):.0f} vs {runs.rate(best, point):.0f}, {best}",
    )


def int8_goals(results: PeerResults) -> list[Goal]:
    """Issue 47's: the int8 variant against the peers, which run the float32 model as their users do."""
    runs = results.runs
    found = [rate_against_best_peer(results, INT8, boxes, target) for boxes, target in ((4, 1.3), (1, 1.15))]
    if FASTAPI in results.peers:
        point = (4, 1)
        found.append(
            Goal(
                "p50 at concurrency 1, 4 box(es): service int8 / FastAPI",
                runs.p50(INT8, point) / runs.p50(FASTAPI, point),
                0.85,
                False,
                f"{runs.p50(INT8, point):.1f} vs {runs.p50(FASTAPI, point):.1f} ms",
            )
        )
    return found


def _cell(values: list[float], digits: int) -> str:
    return " / ".join(f"{v:.{digits}f}" for v in values)


def table(results: PeerResults) -> list[str]:
    names = [c.name for c in results.contenders]
    ratios = [f"{'service' if name == SERVICE else 'int8'} / best peer" for name in results.services]
    lines = [
        "| point | " + " | ".join(names + ratios) + " |",
        "|---|" + "---|" * (len(names) + len(ratios)),
    ]
    runs = results.runs
    for by_rate in (True, False):
        pick = (lambda r: r.requests_per_s) if by_rate else (lambda r: r.p50_ms)
        digits = 0 if by_rate else 1
        for boxes in BOXES:
            for concurrency in CONCURRENCIES:
                point = (boxes, concurrency)
                cells = [_cell(list(map(pick, runs.results[name][point])), digits) for name in names]
                best = results.best_peer(point, by_rate) if results.peers else None
                label = f"{'req/s' if by_rate else 'p50 ms'}, {boxes} box(es), concurrency {concurrency}"
                lines.append(_row(label, cells, results, best, runs.rate if by_rate else runs.p50, point))
    for boxes in BOXES:  # what the server process tree spent per request, whatever else ran
        point = (boxes, 16)
        cells = [_cell(runs.core_ms[name][point], 2) for name in names]
        best = min(results.peers, key=lambda name: runs.cpu(name, point)) if results.peers else None
        label = f"server core-ms per request, {boxes} box(es), concurrency 16"
        lines.append(_row(label, cells, results, best, runs.cpu, point))
    return lines


def _row(
    label: str,
    cells: list[str],
    results: PeerResults,
    best: str | None,
    median: Callable[[str, Point], float],
    point: Point,
) -> str:
    """A table row: its cells, then each service's median over the best peer's."""
    ratios = [
        f"**{median(name, point) / median(best, point):.2f}** ({best})" if best else "-"
        for name in results.services
    ]
    return f"| {label} | " + " | ".join(cells + ratios) + " |"


def render(results: PeerResults) -> str:
    machine = results.machine
    load_end = ", ".join(f"{v:.2f}" for v in results.load_at_end)
    tolerance = GPU_TOLERANCE if on_gpu() else TOLERANCE
    title = "On a GPU (bench_peers --gpu)" if on_gpu() else "Against the frameworks a user would pick instead"
    lines = [
        f"## {title} (bench_peers)" if not on_gpu() else f"## {title}",
        "",
        f"Generated by `{results.command}` in {results.minutes:.0f} min; every figure comes from that run.",
        "",
        f"- Machine: {machine.describe()}; load average at end {load_end}.",
        "- Request: `POST /v1/predict`, multipart/form-data, the README's 640x480 sample JPEG with 1 or 4 "
        "boxes, `cov`, epsilon 0.1 (keypoint coverage); every peer answers with the service's own "
        "decode, crop, float32 model and sets (`benchmarks/peers/pipeline.py`), and before timing each "
        "peer's centres and shape matrices were checked equal to the service's (centres within "
        f"{tolerance:g} px, shape matrices within {tolerance:g} of their largest entry)."
        + (_INT8_CHECK if INT8 in results.services else ""),
        f"- Load: `wrk -t1 -c<concurrency> --latency` on loopback, {results.seconds:g} s per point after a "
        f"warm-up; {results.rounds} round(s), each starting every server in turn (the order reversed in the "
        "second round); each cell gives every round's figure, ratios use the medians.",
        f"- {_gpu_note()}",
        "",
        "### Goals (ratios measured side by side in this run)",
        "",
        "| goal | measured | target | |",
        "|---|---|---|---|",
        *[goal.row() for goal in goals(results)],
        "",
        "### Service and peers",
        "",
        *table(results),
        "",
        "Errors (non-2xx or socket) over the whole run: "
        + ", ".join(f"{c.name} {results.runs.errors(c.name)}" for c in results.contenders)
        + ".",
        "",
        "Server core-ms per request: the CPU time of the server's process tree during the point divided by "
        "the requests it answered. Other jobs on the machine barely move it, so it compares the servers' "
        "efficiency even when the throughput figures are noisy.",
        "",
        "### Settings, and why",
        "",
        *[f"- **{c.name}**: {c.described(on_gpu())}." for c in results.contenders],
        "",
        "### In-process limit (same run)",
        "",
        "The service's own functions called in one process, no HTTP "
        "(`benchmarks/stages.py`): stage medians (wall ms) with one intra-op thread; "
        "core-ms = the process's CPU time per request over those calls (not inflated by other jobs on the "
        "machine); limit = cores / core-ms; best latency = the smallest wall-clock total with one intra-op "
        "thread or one per core.",
        "",
        "| boxes | " + " | ".join(STAGE_NAMES.values()) + " | core-ms | limit req/s | best latency ms |",
        "|---|" + "---|" * (len(STAGE_NAMES) + 3),
        *[
            f"| {limit.boxes} | "
            + " | ".join(f"{limit.stages[s]:.2f}" for s in STAGE_NAMES)
            + f" | {limit.core_ms:.2f} | {limit.requests_per_s:.0f} | {limit.best_latency_ms:.2f} "
            f"({limit.best_threads} thread(s)) |"
            for limit in results.limits
        ],
    ]
    return "\n".join(lines + profile_section(results)) + "\n"


def profile_section(results: PeerResults) -> list[str]:
    profile = results.profile
    if profile is None:
        return []
    lines = ["", "### Where the service's CPU goes under load (py-spy)", ""]
    if profile.problem:
        return [*lines, f"No profile: {profile.problem}."]
    core_ms = results.runs.cpu(SERVICE, (1, 16))
    lines += [
        f"py-spy sampled every thread of the service at concurrency 16 with one box ({profile.samples} "
        f"samples, {profile.running} while threads ran rather than waited); each running sample counts for "
        "the stage of its innermost frame that names one (`benchmarks/peers/profile.py`). ms per request = "
        f"share x the service's server core-ms per request at that point ({core_ms:.2f}).",
        "",
        "| stage | share of running samples | ms per request |",
        "|---|---|---|",
        *[f"| {stage} | {share:.0%} | {share * core_ms:.2f} |" for stage, share in profile.shares.items()],
    ]
    return lines


_INT8_CHECK = (
    " The service int8 is another model (its sets differ a little from float32's): its answers were "
    "checked to name `model.variant` int8, to give every box its keypoints, and to equal its own first "
    "answer in every round."
)


def _gpu_note() -> str:
    """Which onnxruntime providers this machine offers, and what that means for GPU figures."""
    import onnxruntime

    available = onnxruntime.get_available_providers()
    if on_gpu():
        return (
            f"{gpu_names()}. Execution providers available: {', '.join(available)}; every server ran the "
            f"model on `CKS_EXECUTION_PROVIDERS={','.join(execution_providers()[0])}` (the peers' sessions "
            "too, as below); decode, crop and sets stay on the CPU."
        )
    listed = ", ".join(available)
    if "CUDAExecutionProvider" not in available:
        return (
            f"Execution providers available: {listed}. No GPU build of onnxruntime here: the GPU figures "
            'are the "On a GPU" section (`bench_peers --gpu` on a GPU machine; settings in '
            'docs/operations.md, "Serving from a GPU").'
        )
    return f"Execution providers available: {listed} (the service ran with its `CKS_EXECUTION_PROVIDERS`)."
