"""Smoke test of benchmarks.bench_ab: each revision's server runs that revision's code (not the
working tree's, nor the installed package's), and the summary pairs the runs (timings are never
asserted; no server is started here)."""

from __future__ import annotations

import subprocess
from pathlib import Path

from benchmarks.bench_ab import POINTS, ROOT, export, paced_bodies, paced_summary, server_argv_env, summary
from benchmarks.harness import load_sample
from service.api.predict.frame_input import parse_frame
from service.detector.manifest import load_manifest
from service.infra.settings import DEFAULT_MODEL_DIR


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


def test_the_paced_frames_are_1080p_regions_the_service_parses() -> None:
    bodies = paced_bodies(load_sample())
    manifest = load_manifest(DEFAULT_MODEL_DIR)
    frames = [
        (body, content_type) for path, body, content_type in bodies.values() if path == "/v1/predict/frame"
    ]
    assert len(frames) == 2
    for body, content_type in frames:
        frame, parameters = parse_frame(content_type, body, manifest)
        assert (frame.width, frame.height) == (1920, 1080) and len(parameters.instances) in (1, 4)
        assert frame.regions and all(region.encoding == "rgb8" for region in frame.regions)


def test_the_paced_summary_gives_the_median_of_paired_latency_ratios() -> None:
    runs = {
        ("A", "p"): [(10.0, 5.0), (20.0, 5.0), (10.0, 5.0)],
        ("B", "p"): [(9.5, 5.0), (20.0, 5.0), (11.0, 5.0)],
    }
    lines = paced_summary(runs, 30)
    assert lines[0].startswith("paced, 30 ms apart") and " 1.000 [0.950..1.100]" in lines[1], lines
