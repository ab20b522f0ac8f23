"""Smoke test of benchmarks.bench_drift_streams on a few rendered frames: the table's shape, both
methods, every shift, the runs' seeds drawn afresh or replayed; never its figures."""

from __future__ import annotations

from pathlib import Path

import pytest

from benchmarks.bench_drift_streams import METHODS, main
from training.streams import SHIFTS


def test_the_benchmark_prints_false_alarms_and_delays_for_both_methods(
    tmp_path: Path, capsys: pytest.CaptureFixture[str]
) -> None:
    arguments = ["--frames", "2", "--sequences", "3", "--shift-sequences", "1", "--cache", str(tmp_path)]
    rows = main([*arguments, "--runs", "2"])
    assert list(rows) == list(METHODS)
    for rate, delays in rows.values():
        assert rate >= 0 and set(delays) == set(SHIFTS) - {"none"}
        assert all(delay.endswith("/2)") for delay in delays.values())  # raised in k of the 2 runs
    printed = capsys.readouterr().out
    assert "false alarms / 10k frames" in printed and "heavy_occlusion" in printed
    seeds = printed.split("scene seeds of this run (shift i: seed + i): ")[1].split("\n")[0].split()
    assert len(seeds) == 2 and all(int(seed) >= 1_000_000 for seed in seeds)
    assert len(list(tmp_path.glob("*/frames-*.pkl"))) == 1 + 2 * (len(SHIFTS) - 1)  # cached
    again = main([*arguments, "--seeds", *seeds])
    assert again == rows
