"""Smoke test of benchmarks.bench_pose: it runs and reports every step and method; never its timings."""

from __future__ import annotations

from benchmarks.bench_pose import main


def test_the_benchmark_reports_cost_and_tightness(capsys) -> None:
    main(["--images", "1", "--epsilon", "0.3", "--samples", "20", "--splits", "1", "--programs", "30"])
    out = capsys.readouterr().out
    for step in ("estimate", "inner"):
        assert any(line.startswith(step) for line in out.splitlines()), out
    assert "tightness (outer / inner, median / p90)" in out
    for method in ("whole", "splits 1", "search 30"):
        assert any(line.strip().startswith(method) for line in out.splitlines()), out
    assert out.count("certified bounds containing the true error") == 3
