"""Service vs raw onnxruntime, memory and tuning: the measurements that need a live server."""

from __future__ import annotations

import os
from collections.abc import Callable
from dataclasses import dataclass, field
from pathlib import Path

import numpy as np

from benchmarks.service_bench import raw
from benchmarks.service_bench.inputs import Sample
from benchmarks.service_bench.loadgen import LoadResult, post_requests, run_wrk, write_script
from benchmarks.service_bench.server import Server, serve
from service.detector.images import decode_image
from service.detector.manifest import load_manifest
from service.detector.preprocess import build_batch

CONCURRENCIES = (1, 4, 16)
INSTANCE_COUNTS = (1, 4)
BATCHED_CROPS = 16
SETTING_NAMES = ("workers", "inference_threads", "max_concurrent_inferences", "cpu_workers")


@dataclass(frozen=True)
class Plan:
    """How long each point runs; --quick shortens everything."""

    seconds: float
    tuning_seconds: float
    warmup_seconds: float
    memory_requests: tuple[int, int]

    @staticmethod
    def for_mode(quick: bool, seconds: float | None = None) -> Plan:
        """``seconds``: per headline point instead of the mode's (tuning points at most as long)."""
        plan = Plan(2.0, 2.0, 1.0, (200, 2000)) if quick else Plan(10.0, 6.0, 2.0, (1000, 10000))
        if seconds is None:
            return plan
        return Plan(seconds, min(seconds, plan.tuning_seconds), plan.warmup_seconds, plan.memory_requests)


@dataclass
class Point:
    """One (instances, concurrency) point: the service and the raw session side by side."""

    instances: int
    concurrency: int
    service: LoadResult
    raw: raw.RawResult
    load_1m: float = field(default_factory=lambda: os.getloadavg()[0])  # after the point

    @property
    def raw_requests_per_s(self) -> float:
        return self.raw.runs_per_s  # one run per request-equivalent

    @property
    def ratio(self) -> float:
        return self.service.requests_per_s / self.raw_requests_per_s


@dataclass
class Memory:
    after: list[tuple[int, int]] = field(default_factory=list)  # (requests so far, VmRSS KiB)

    @property
    def growth(self) -> float:
        (_, first), (_, last) = self.after[0], self.after[-1]
        return last / first - 1


@dataclass
class Workspace:
    """Request bodies, wrk scripts and input batches, written once to a temp dir."""

    directory: Path
    model_dir: Path
    settings: dict[str, int]
    scripts: dict[tuple[int, str], Path] = field(default_factory=dict)  # (instances, "multipart"|"json")
    bodies: dict[int, tuple[bytes, str]] = field(default_factory=dict)
    batches: dict[int, Path] = field(default_factory=dict)  # crops -> .npy

    def env(self, **overrides: int) -> dict[str, str]:
        merged = {**self.settings, **overrides}
        return {
            "CKS_MODEL_DIR": str(self.model_dir),
            **{f"CKS_{k.upper()}": str(v) for k, v in merged.items()},
        }


def prepare(directory: Path, model_dir: Path, sample: Sample, settings: dict[str, int]) -> Workspace:
    space = Workspace(directory, model_dir, settings)
    manifest = load_manifest(model_dir)
    image = decode_image(sample.jpeg, 10**9)
    for count in INSTANCE_COUNTS:
        subset = sample.with_instances(count)
        space.bodies[count] = subset.multipart_body()
        for kind, (body, content_type) in (
            ("multipart", subset.multipart_body()),
            ("json", subset.json_body()),
        ):
            folder = directory / f"{kind}-{count}"
            folder.mkdir()
            space.scripts[count, kind] = write_script(folder, body, content_type)
    for crops in (*INSTANCE_COUNTS, BATCHED_CROPS):
        batch, _ = build_batch(image, sample.with_instances(crops).boxes, manifest)
        space.batches[crops] = directory / f"batch-{crops}.npy"
        np.save(space.batches[crops], batch)
    return space


def raw_point(
    space: Workspace, crops: int, concurrency: int, seconds: float, **overrides: int
) -> raw.RawResult:
    """The raw session in the process layout and thread settings of the headline (plus ``overrides``)."""
    settings = {**space.settings, **overrides}
    return raw.measure_in_subprocess(
        space.model_dir,
        settings["inference_threads"],
        space.batches[crops],
        concurrency,
        seconds,
        processes=settings["workers"],
    )


def warm_up(server: Server, space: Workspace, plan: Plan) -> None:
    for count in INSTANCE_COUNTS:
        run_wrk(server.url, space.scripts[count, "multipart"], 4, plan.warmup_seconds)


def memory(server: Server, space: Workspace, plan: Plan, log: Callable[[str], None]) -> Memory:
    """VmRSS after the first and the last of ``plan.memory_requests`` 1-instance requests."""
    result, done = Memory(), 0
    body, content_type = space.bodies[1]
    for target in plan.memory_requests:
        load = post_requests(server.url, body, content_type, target - done, concurrency=16)
        done += load.requests
        result.after.append((done, server.rss_kib()))
        log(f"memory: {done} requests, VmRSS {result.after[-1][1] / 1024:.1f} MiB, {load.errors} errors")
    return result


def headline(
    space: Workspace, plan: Plan, log: Callable[[str], None], with_memory: bool = True
) -> tuple[list[Point], Memory | None, dict]:
    """Every (instances, concurrency) point, service then raw, plus memory and the JSON body."""
    points, extra = [], {}
    with serve(space.env(), log=space.directory / "server.log") as server:
        warm_up(server, space, plan)
        mem = memory(server, space, plan, log) if with_memory else None
        for count in INSTANCE_COUNTS:
            for concurrency in CONCURRENCIES:
                service = run_wrk(server.url, space.scripts[count, "multipart"], concurrency, plan.seconds)
                baseline = raw_point(space, count, concurrency, plan.seconds)
                points.append(Point(count, concurrency, service, baseline))
                log(format_point(points[-1]))
            extra[f"json-{count}"] = run_wrk(server.url, space.scripts[count, "json"], 16, plan.seconds)
            log(f"JSON body, {count} instance(s), c=16: {extra[f'json-{count}'].requests_per_s:.1f} req/s")
    extra["batched-1"] = raw_point(space, BATCHED_CROPS, 1, plan.tuning_seconds)
    crops_per_s = extra["batched-1"].runs_per_s * BATCHED_CROPS
    log(f"raw batches of {BATCHED_CROPS} crops, 1 caller: {crops_per_s:.1f} crops/s")
    return points, mem, extra


def format_point(point: Point) -> str:
    s = point.service
    return (
        f"{point.instances} inst c={point.concurrency:<2}  service {s.requests_per_s:7.1f} req/s "
        f"p50 {s.p50_ms:7.1f} ms p99 {s.p99_ms:7.1f} ms  raw {point.raw_requests_per_s:7.1f}/s  "
        f"ratio {point.ratio:.2f}  errors {s.errors}  wrk cpu {s.loadgen_cpu_share:.0%}  "
        f"load {point.load_1m:.1f}"
    )


@dataclass
class Variant:
    """One tuning trial: settings changed from the headline, measured at concurrency 16."""

    label: str
    overrides: dict[str, int]
    points: list[Point] = field(default_factory=list)


TUNING = (
    Variant("CKS_WORKERS=2 (a process per core)", {"workers": 2}),
    Variant("CKS_INFERENCE_THREADS=2 (two intra-op threads per run)", {"inference_threads": 2}),
    Variant("CKS_MAX_CONCURRENT_INFERENCES=16", {"max_concurrent_inferences": 16}),
    Variant("CKS_CPU_WORKERS=2", {"cpu_workers": 2}),
)


def tuning(
    space: Workspace, plan: Plan, variants: tuple[Variant, ...], log: Callable[[str], None]
) -> list[Variant]:
    raws: dict[tuple, raw.RawResult] = {}
    done = []
    for template in variants:
        variant = Variant(template.label, template.overrides)
        env = space.env(**variant.overrides)
        with serve(env, log=space.directory / "server.log") as server:
            warm_up(server, space, plan)
            for count in INSTANCE_COUNTS:
                service = run_wrk(server.url, space.scripts[count, "multipart"], 16, plan.tuning_seconds)
                layout = {**space.settings, **variant.overrides}
                key = (layout["inference_threads"], layout["workers"], count)
                if key not in raws:
                    raws[key] = raw_point(space, count, 16, plan.tuning_seconds, **variant.overrides)
                variant.points.append(Point(count, 16, service, raws[key]))
                log(f"{variant.label}: {format_point(variant.points[-1])}")
        done.append(variant)
    return done
