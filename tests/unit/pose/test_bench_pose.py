"""Smoke test of benchmarks.bench_pose: it runs and reports every step; never its timings."""

from __future__ import annotations

from benchmarks.bench_pose import main


def test_the_benchmark_reports_cost_and_tightness(capsys) -> None:
    main(["--images", "1", "--epsilon", "0.3", "--samples", "20"])
    out = capsys.readouterr().out
    for step in ("estimate", "inner", "outer"):
        assert any(line.startswith(step) for line in out.splitlines()), out
    assert "tightness (outer / inner, median)" in out
    assert "certified bounds containing the true error" in out
