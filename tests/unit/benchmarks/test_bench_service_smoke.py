"""Smoke test of benchmarks.bench_service: structure of its output, never its timings (no wrk)."""

from __future__ import annotations

import math
from pathlib import Path

import pytest

from benchmarks import bench_service
from benchmarks.bench_service import CONCURRENCIES, Point, RawResult, Results, raw_session, render
from benchmarks.harness import BOXES, LoadResult, Machine, Sample, load_sample, parse_wrk
from benchmarks.stages import STAGES, service_state, stage_breakdown
from service.detector.images import decode_image
from service.detector.manifest import load_manifest
from service.detector.preprocess import build_batch
from service.infra.settings import DEFAULT_MODEL_DIR

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
def sample() -> Sample:
    return load_sample()


def test_sample_builds_the_multipart_body(sample: Sample) -> None:
    four = sample.with_instances(4)
    assert len(four.objects) == 4 and four.boxes.shape == (4, 4)
    body, content_type = four.multipart_body()
    assert content_type.startswith("multipart/form-data; boundary=") and sample.jpeg in body


@pytest.mark.parametrize("instances", BOXES)
def test_breakdown_reports_every_stage(sample: Sample, instances: int) -> None:
    with service_state(DEFAULT_MODEL_DIR, inference_threads=1) as state:
        stages = stage_breakdown(state, sample.with_instances(instances), iterations=3)
    assert list(stages) == [*STAGES, "total"]
    assert all(math.isfinite(ms) and ms >= 0 for ms in stages.values())
    assert stages["total"] == pytest.approx(sum(stages[s] for s in STAGES))


def test_the_raw_session_runs_in_processes_of_its_own(sample: Sample) -> None:
    manifest = load_manifest(DEFAULT_MODEL_DIR)
    batch, _ = build_batch(decode_image(sample.jpeg, 10**9), sample.with_instances(1).boxes, manifest)
    result = raw_session(DEFAULT_MODEL_DIR, 1, batch, concurrency=3, seconds=0.3, processes=2)
    assert result.runs_per_s > 0 and result.p50_ms > 0


def test_wrk_output_is_parsed() -> None:
    result = parse_wrk(WRK_OUTPUT, concurrency=4, cpu_seconds=0.2)
    assert (result.requests, result.errors, result.concurrency) == (198, 3, 4)
    assert result.requests_per_s == pytest.approx(98.51)
    assert (result.p50_ms, result.p99_ms) == (pytest.approx(38.5), pytest.approx(1200.0))
    assert result.loadgen_cpu_share == pytest.approx(0.2 / 2.01)


def _results() -> Results:
    def load(rps: float) -> LoadResult:
        return LoadResult(16, int(rps * 10), 10.0, rps, 100.0, 200.0, 0, 0.01)

    points = [
        Point(n, c, load(100.0 / n), RawResult(120.0 / n, 50.0), 1.0) for n in BOXES for c in CONCURRENCIES
    ]
    stages = {stage: 1.0 for stage in STAGES}
    return Results(
        command="python -m benchmarks.bench_service",
        machine=Machine(2, "test CPU", (0.5, 0.5, 0.5), "3.11", "1.0"),
        load_at_end=(1.0, 0.8, 0.6),
        model="`test`",
        settings={name: 1 for name in bench_service.SETTING_NAMES},
        points=points,
        memory=[(1000, 200_000), (10001, 201_000)],
        breakdown={n: {**stages, "total": float(len(STAGES))} for n in BOXES},
    )


def test_the_section_gives_goals_tables_and_memory(tmp_path: Path) -> None:
    text = render(_results())
    for heading in ("### Goals", "### Service vs raw", "### Where the time goes", "### Memory"):
        assert heading in text
    assert "`CKS_INFERENCE_THREADS=1`" in text and "| 10001 | 196.3 |" in text
    assert "| service / raw throughput at concurrency 16, 4 instance(s) >= 0.85 | 0.83 | **no** |" in text
    assert "| RSS after 10001 requests within 5% of after 1000 | +0.5% | yes |" in text
