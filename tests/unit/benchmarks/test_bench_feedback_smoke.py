"""Smoke test of benchmarks.bench_feedback on a few rendered frames: false alarms, each shift's
and run's coverage and drift alarms, static and adaptive miscoverage against ACI's bound,
retention's cost; never its figures."""

from __future__ import annotations

from pathlib import Path

import pytest

from benchmarks.bench_feedback import LABELS_MOVED, SHIFT_SEEDS, main


def test_the_benchmark_reports_alarms_bounds_and_retention_for_fresh_seeds(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    arguments = ["--frames", "3", "--sequences", "6", "--shift-sequences", "3", "--delay", "2"]
    summary = main(
        [*arguments, "--runs", "2", "--requests", "3", "--paired-orders", "1", "--cache", str(tmp_path)]
    )
    printed = capsys.readouterr().out
    assert "false alarms in 18 labelled frames" in printed
    assert "frames from the shift to the alarm, min/median/max" in printed and "retention cost" in printed
    assert list(summary["shifts"]) == [*SHIFT_SEEDS, LABELS_MOVED]
    for runs in summary["shifts"].values():
        assert len(runs) == 2 and all(seed >= 1_000_000 for seed in runs)
        for alarm, adaptive, static, bound, whole_adaptive, whole_bound, drift in runs.values():
            assert 0 <= adaptive <= 1 and 0 <= static <= 1 and 0 <= whole_adaptive <= 1
            assert bound > whole_bound > 0  # fewer labels after the shift than in the whole stream
            assert all(frames is None or frames > 0 for frames in (alarm, drift))
    assert printed.count("(raised in): coverage") == len(SHIFT_SEEDS) + 1  # and the drift alarm, per shift
    assert printed.count("paired, 2 streams of") == len(SHIFT_SEEDS) + 1  # the former alarm beside
    without, with_retain, _ = summary["retention"]
    assert without > 0 and with_retain > 0
