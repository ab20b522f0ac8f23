"""Smoke test of benchmarks.bench_drift_streams on a few rendered frames: the table's shape, both
methods, every shift; never its figures."""

from __future__ import annotations

from pathlib import Path

import pytest

from benchmarks.bench_drift_streams import METHODS, main
from training.streams import SHIFTS


def test_the_benchmark_prints_false_alarms_and_delays_for_both_methods(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    arguments = ["--frames", "2", "--sequences", "3", "--shift-sequences", "1", "--orders", "1"]
    rows = main([*arguments, "--cache", str(tmp_path)])
    assert list(rows) == list(METHODS)
    for rate, delays in rows.values():
        assert rate >= 0 and set(delays) == set(SHIFTS) - {"none"}
    printed = capsys.readouterr().out
    assert "false alarms / 10k frames" in printed and "heavy_occlusion" in printed
    assert len(list(tmp_path.glob("*/frames-*.pkl"))) == len(SHIFTS)  # cached for the next run
    again = main([*arguments, "--cache", str(tmp_path)])
    assert again == rows
