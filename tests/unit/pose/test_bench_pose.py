"""Smoke test of benchmarks.bench_pose: it runs and reports every step and method, and the whole answer per
instance on single frames and on a rendered camera sequence; never its timings."""

from __future__ import annotations

from benchmarks.bench_pose import main


def test_the_benchmark_reports_cost_and_tightness(capsys) -> None:
    main(
        ["--images", "1", "--epsilon", "0.3", "--samples", "20", "--splits", "1", "--programs", "30"]
        + ["--sequences", "1", "--frames", "2"]
    )
    out = capsys.readouterr().out
    for step in ("estimate", "inner"):
        assert any(line.startswith(step) for line in out.splitlines()), out
    assert "tightness (outer / inner, median / p90)" in out
    for method in ("whole", "splits 1", "search 30"):
        assert any(line.strip().startswith(method) for line in out.splitlines()), out
    assert out.count("certified bounds containing the true error") == 5  # 3 methods, 2 per-instance lines
    assert "single frames (samples)" in out and "camera sequences (1 x 2 frames, seed 0)" in out
