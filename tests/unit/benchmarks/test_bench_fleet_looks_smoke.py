"""Smoke test of benchmarks.bench_fleet_looks on a small fleet: every figure printed; never its values."""

from __future__ import annotations

import pytest

from benchmarks.bench_fleet_looks import main


def test_the_benchmark_prints_the_decision_and_share_costs(capsys: pytest.CaptureFixture[str]) -> None:
    figures = main(["--replicas", "2", "--frames", "50", "--looks", "10", "--undecided", "5"])
    assert set(figures) == {"decide 5", "encode", "decode", "megabytes", "megabytes without frames"}
    assert figures["megabytes"] > figures["megabytes without frames"] > 0
    printed = capsys.readouterr().out
    assert "deciding 5 undecided looks of each of 2 replicas" in printed and "MB with 50 frames" in printed
