"""Does the JPEG window extension earn its place? A paired A/B on the user's figure:

    python -m benchmarks.ab_jpeg_window --rounds 6 --per-round 10

A whole 1920x1080 and 3840x2160 JPEG frame with 4 boxes to POST /v1/predict, frames 30 ms apart,
two servers of this tree side by side, one without the extension (whole decodes); rounds alternate
which goes first. Prints the median latencies and the paired median of whole/window per round.
"""

from __future__ import annotations

import argparse
import json
import statistics
import tempfile
import time
from contextlib import ExitStack
from pathlib import Path

import httpx
from keypoint_client.frames import jpeg_bytes

from benchmarks.bench_ab import export, server_argv_env
from benchmarks.bench_frames import make_point
from benchmarks.harness import free_port, launch, load_sample

SIZES = ((1920, 1080), (3840, 2160))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--rounds", type=int, default=6)
    parser.add_argument("--per-round", type=int, default=10)
    args = parser.parse_args()
    work = Path(tempfile.mkdtemp())
    trees = {"window": export("HEAD", work / "window"), "whole": export("HEAD", work / "whole")}
    for extension in (trees["whole"] / "service" / "detector").glob("_jpeg_window*.so"):
        extension.unlink()
    points = {size: make_point(load_sample(), *size, 4) for size in SIZES}
    with ExitStack() as stack:
        clients = {}
        for name, tree in trees.items():
            port = free_port()
            argv, env = server_argv_env(tree, work / f"data-{name}", port)
            server = stack.enter_context(launch(argv, env, port, work / f"{name}.log"))
            clients[name] = stack.enter_context(httpx.Client(base_url=server.url, timeout=60))

        def latency(name: str, size: tuple[int, int]) -> float:
            files = {
                "image": ("frame.jpg", jpeg_bytes(points[size].frame), "image/jpeg"),
                "request": (None, json.dumps(points[size].parameters)),
            }
            started = time.perf_counter()
            response = clients[name].post("/v1/predict", files=files)
            took = time.perf_counter() - started
            assert response.status_code == 200, response.text
            time.sleep(0.03)  # a camera's cadence: the server idles between frames
            return took

        for size in SIZES:
            for name in clients:
                [latency(name, size) for _ in range(5)]  # warm-up
            medians: dict[str, list[float]] = {name: [] for name in clients}
            for round_number in range(args.rounds):
                for name in list(clients)[:: 1 if round_number % 2 == 0 else -1]:
                    medians[name].append(
                        statistics.median(latency(name, size) for _ in range(args.per_round))
                    )
            ratios = [
                whole / window for whole, window in zip(medians["whole"], medians["window"], strict=True)
            ]
            window, whole = (statistics.median(medians[name]) * 1e3 for name in ("window", "whole"))
            print(
                f"{size[0]}x{size[1]}, 4 boxes: p50 window {window:.1f} ms, whole {whole:.1f} ms;"
                " whole/window paired median"
                f" {statistics.median(ratios):.3f} [{min(ratios):.3f}..{max(ratios):.3f}]"
            )


if __name__ == "__main__":
    main()
