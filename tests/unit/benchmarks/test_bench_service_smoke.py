"""Smoke test of benchmarks.bench_service: structure of its output, never its timings (no wrk)."""

from __future__ import annotations

import math
from pathlib import Path

import pytest

from benchmarks.service_bench import report, runs
from benchmarks.service_bench.breakdown import STAGES, service_state, stage_breakdown
from benchmarks.service_bench.inputs import Sample, load_sample
from benchmarks.service_bench.loadgen import LoadResult, parse_wrk
from benchmarks.service_bench.machine import Machine
from benchmarks.service_bench.offline import Calibration, PostProcessing
from benchmarks.service_bench.raw import RawResult
from service.infra.settings import Settings

WRK_OUTPUT = """\
Running 2s test @ http://127.0.0.1:40000/v1/predict
  1 threads and 4 connections
  Thread Stats   Avg      Stdev     Max   +/- Stdev
    Latency    40.12ms   10.00ms  120.50ms   70.00%
    Req/Sec    99.00     10.00   120.00     80.00%
  Latency Distribution
     50%   38.50ms
     75%   45.00ms
     90%   52.00ms
     99%    1.20s
  198 requests in 2.01s, 1.50MB read
  Non-2xx or 3xx responses: 3
Requests/sec:     98.51
Transfer/sec:    764.00KB
"""


@pytest.fixture(scope="module")
def model_dir() -> Path:
    return Path(Settings().model.directory).resolve()


@pytest.fixture(scope="module")
def sample(model_dir: Path) -> Sample:
    return load_sample(model_dir / "samples")


def test_sample_builds_both_request_bodies(sample: Sample) -> None:
    four = sample.with_instances(4)
    assert len(four.objects) == 4 and four.boxes.shape == (4, 4)
    body, content_type = four.multipart_body()
    assert content_type.startswith("multipart/form-data; boundary=") and sample.jpeg in body
    body, content_type = four.json_body()
    assert content_type == "application/json" and b'"image_base64"' in body


@pytest.mark.parametrize("instances", [1, 4])
def test_breakdown_reports_every_stage(model_dir: Path, sample: Sample, instances: int) -> None:
    with service_state(model_dir, inference_threads=1) as state:
        stages = stage_breakdown(state, sample.with_instances(instances), iterations=3)
    assert list(stages) == [*STAGES, "total"]
    assert all(math.isfinite(ms) and ms >= 0 for ms in stages.values())
    assert stages["total"] == pytest.approx(sum(stages[s] for s in STAGES))


def test_wrk_output_is_parsed() -> None:
    result = parse_wrk(WRK_OUTPUT, concurrency=4, cpu_seconds=0.2)
    assert (result.requests, result.errors, result.concurrency) == (198, 3, 4)
    assert result.requests_per_s == pytest.approx(98.51)
    assert (result.p50_ms, result.p99_ms) == (pytest.approx(38.5), pytest.approx(1200.0))
    assert result.loadgen_cpu_share == pytest.approx(0.2 / 2.01)


def _synthetic_results() -> report.Results:
    def load(rps: float) -> LoadResult:
        return LoadResult(16, int(rps * 10), 10.0, rps, 100.0, 200.0, 0, 0.01)

    def raw_result(runs_per_s: float, batch: int = 1) -> RawResult:
        return RawResult(16, batch, runs_per_s, 50.0, 90.0)

    settings = {name: Settings().value(name) for name in runs.SETTING_NAMES}
    points = [
        runs.Point(n, c, load(100.0 / n), raw_result(120.0 / n), load_1m=1.0)
        for n in runs.INSTANCE_COUNTS
        for c in runs.CONCURRENCIES
    ]
    tuned = [
        runs.Variant(
            v.label,
            v.overrides,
            [runs.Point(n, 16, load(110.0 / n), raw_result(120.0 / n), 1.0) for n in runs.INSTANCE_COUNTS],
        )
        for v in runs.TUNING
    ]
    stages = {stage: 1.0 for stage in STAGES}
    return report.Results(
        command="python -m benchmarks.bench_service",
        quick=False,
        machine=Machine(2, "test CPU", (0.5, 0.5, 0.5), "3.11", "1.0"),
        load_at_end=(1.0, 0.8, 0.6),
        model="`test`",
        settings=settings,
        points=points,
        memory=runs.Memory([(1000, 200_000), (10001, 201_000)]),
        extra={
            "json-1": load(90.0),
            "json-4": load(20.0),
            "batched-1": raw_result(8.0, runs.BATCHED_CROPS),
        },
        breakdown={n: {**stages, "total": float(len(STAGES))} for n in runs.INSTANCE_COUNTS},
        post=[PostProcessing(kind, 100.0, 2.0) for kind in ("peak", "var", "cov")],
        calibration=Calibration(100, 1.0, 0.1, 0.12, 100_000),
        tuning=tuned,
    )


def test_report_renders_every_section_and_tuning_row() -> None:
    text = report.render(_synthetic_results())
    for heading in ("## Goals", "## Service vs raw", "## Where the time goes", "## Tuning", "## Memory"):
        assert heading in text
    assert "`CKS_INFERENCE_THREADS=" in text  # the headline settings include the threads
    for variant in runs.TUNING:
        assert f"| {variant.label} |" in text
    assert "patched_serve" not in text and "spin" not in text


def test_tuning_points_run_at_most_as_long_as_the_headline_points() -> None:
    assert runs.Plan.for_mode(False, 4.0).tuning_seconds == 4.0
    assert runs.Plan.for_mode(False, 20.0).tuning_seconds == runs.Plan.for_mode(False).tuning_seconds
