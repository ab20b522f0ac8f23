"""Smoke test of benchmarks.bench_frames: its frames are what it says, a short run against real
servers checks the answers and writes its section whole (timings are never asserted)."""

from __future__ import annotations

from pathlib import Path

import httpx
import pytest

from benchmarks.bench_frames import CONTENDERS, Contenders, main, make_point
from benchmarks.harness import load_sample, serve


@pytest.mark.parametrize(("width", "height", "boxes"), [(640, 480, 1), (1920, 1080, 4), (3840, 2160, 4)])
def test_frames_have_their_size_and_boxes_inside(width: int, height: int, boxes: int) -> None:
    point = make_point(load_sample(), width, height, boxes)
    assert point.frame.shape == (height, width, 3) and point.frame.flags.c_contiguous
    assert len(point.parameters["instances"]) == boxes
    for instance in point.parameters["instances"]:
        x, y, w, h = instance["bbox"]
        assert x >= 0 and x + w <= width and y >= 0 and y + h <= height


def test_regions_cut_with_another_padding_are_refused_not_timed(tmp_path: Path) -> None:
    point = make_point(load_sample(), 640, 480, 1)
    with serve({}, log=tmp_path / "service.log") as server:
        contenders = Contenders(server, server, server, padding=0.0)
        try:
            with pytest.raises(httpx.HTTPStatusError, match="422"):
                contenders.regions(point)
        finally:
            contenders.close()


def test_a_short_run_writes_its_section(tmp_path: Path) -> None:
    output = tmp_path / "performance.md"
    output.write_text("# Performance\n\n<!-- bench_service:begin -->\nold\n<!-- bench_service:end -->\n")
    main(["--rounds", "2", "--sizes", "640x480", "--output", str(output)])
    written = output.read_text()
    assert written.index("bench_frames:begin") < written.index("bench_service:begin")
    assert "| 640x480, 1 box |" in written and "| 640x480, 4 boxes |" in written
    assert "each request 50 ms after the previous one ended" in written
    for name in CONTENDERS:
        assert name in written
    assert "| FastAPI whole JPEG / service int8 raw regions, time (CPU) |" in written
    assert "Goal (issue 47): at 1920x1080 with 4 boxes, the service int8" in written
    assert "not measured in this run" in written
