"""Smoke test of benchmarks.bench_ab: each revision's server runs that revision's code (not the
working tree's, nor the installed package's), and the summary pairs the runs (timings are never
asserted; no server is started here)."""

from __future__ import annotations

import subprocess
from pathlib import Path

from benchmarks.bench_ab import POINTS, ROOT, export, server_argv_env, summary


def test_a_revision_is_served_from_its_own_export(tmp_path: Path) -> None:
    tree = export("HEAD", tmp_path / "tree")
    argv, env = server_argv_env(tree, tmp_path / "data", 8000)
    python, *flags = argv[: argv.index("-m")]
    probe = "import service.api.predict.predict_presenter as m; print(m.__file__)"
    # Run from the working tree: its own service/ must not win over the export's.
    where = subprocess.run([python, *flags, "-c", probe], env=env, cwd=ROOT, capture_output=True, text=True)
    assert where.returncode == 0, where.stderr
    assert Path(where.stdout.strip()) == tree / "service" / "api" / "predict" / "predict_presenter.py"


def test_the_summary_gives_the_median_of_paired_ratios() -> None:
    runs = {}
    for point in POINTS:
        runs["A", point] = [(100.0, 10.0), (50.0, 20.0), (100.0, 10.0)]
        runs["B", point] = [(95.0, 10.5), (50.0, 20.0), (110.0, 9.0)]  # ratios 0.95, 1.00, 1.10
    lines = summary(runs)
    assert len(lines) == 1 + len(POINTS)
    assert all(" 1.000 [0.950..1.100]" in line for line in lines[1:]), lines
