"""Smoke test of benchmarks.bench_memory: a real server, a few hundred requests, the structure of
its report (never its figures), with the light load generator so that wrk is not needed."""

from __future__ import annotations

import re

import pytest

from benchmarks import bench_memory
from benchmarks.service_bench.runs import Memory


def test_a_short_run_reads_rss_at_each_checkpoint_and_gives_a_verdict(capsys) -> None:
    bench_memory.main(
        ["--requests", "300", "--first", "100", "--every", "100", "--load", "python", "--concurrency", "4"]
    )
    out = capsys.readouterr().out
    readings = re.findall(r"after\s+(\d+) requests: VmRSS\s+([\d.]+) MiB .*, (\d+) errors\)", out)
    assert [int(done) for done, _, _ in readings] == [100, 200, 300], out
    assert all(float(mib) > 50 for _, mib, _ in readings), out  # the model alone takes more
    assert all(errors == "0" for _, _, errors in readings), out
    verdict = r"RSS after 300 requests / after 100: [\d.]+ \([+-][\d.]+%\); goal within 5%: (met|NOT met)"
    assert re.search(verdict, out), out


def test_checkpoints_start_at_the_first_reading_and_end_at_the_total() -> None:
    assert bench_memory.checkpoints(1_000, 10_000, 100_000) == [1_000, *range(10_000, 100_001, 10_000)]
    assert bench_memory.checkpoints(100, 1_000, 300) == [100, 300]


@pytest.mark.parametrize(("last_kib", "verdict"), [(1040, ": met"), (1060, ": NOT met"), (940, ": NOT met")])
def test_the_verdict_is_growth_within_five_percent_either_way(last_kib: int, verdict: str) -> None:
    assert bench_memory.verdict(Memory([(1000, 1000), (100_000, last_kib)])).endswith(verdict)


def test_a_first_reading_beyond_the_total_is_refused() -> None:
    with pytest.raises(SystemExit):
        bench_memory.parse_args(["--requests", "100", "--first", "100"])
