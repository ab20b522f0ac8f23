"""A paired A/B of two revisions on the README's request: does a mechanism earn its place?

    python -m benchmarks.bench_ab main HEAD                  # ~4 min: 6 rounds, 4 s a point
    python -m benchmarks.bench_ab main my-branch --rounds 12 --seconds 3
    python -m benchmarks.bench_ab main HEAD --model-dir models/lmo-synth-unet-int8

Each revision is exported (``git archive``, with this tree's built C kernel copied in) and served
with its defaults (``keypoint-service serve``, the bundled model or ``--model-dir``), both servers
up side by side and loaded one at a time: POST /v1/predict, multipart, the sample image with 1 and 4 boxes, at
concurrency 1 and 16 (wrk); then frames as a camera sends them, one at a time ``--gap-ms`` (30)
apart (a robot's loop, where the server sits idle between frames): a 1920x1080 frame's regions
as raw pixels (POST /v1/predict/frame) with 4 and 1 boxes, and the README's request with 1 box.
Rounds alternate which revision goes first. Prints every run, then per point the medians and
the median of the paired ratios B/A with their spread: requests/s (wrk) or the median latency
(paced frames), and server core-ms per request; and the load average, which a shared machine's
figures depend on.
"""

from __future__ import annotations

import argparse
import json
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
import time
from contextlib import ExitStack
from pathlib import Path

import httpx

from benchmarks.bench_frames import frame_parts, make_point
from benchmarks.harness import (
    ROOT,
    Requests,
    Sample,
    Server,
    free_port,
    launch,
    load_sample,
    require_wrk,
    run_wrk,
)
from service.infra.settings import DEFAULT_MODEL_DIR

POINTS = [(boxes, concurrency) for boxes in (1, 4) for concurrency in (1, 16)]
PACED_REQUESTS = 20  # per point, revision and round


def export(revision: str, directory: Path) -> Path:
    """``revision``'s tracked files in ``directory``, with this tree's built extensions (untracked;
    a revision that does not import one leaves it unused)."""
    directory.mkdir()
    archive = subprocess.run(["git", "-C", str(ROOT), "archive", revision], check=True, capture_output=True)
    subprocess.run(["tar", "-x", "-C", str(directory)], input=archive.stdout, check=True)
    for extension in (ROOT / "service").rglob("_*.so"):
        shutil.copy(extension, directory / extension.relative_to(ROOT))
    return directory


def server_argv_env(
    tree: Path, data_dir: Path, port: int, model_dir: Path = DEFAULT_MODEL_DIR
) -> tuple[list[str], dict[str, str]]:
    """How to serve ``tree``'s code (``-P``: not the working directory's) with ``model_dir``."""
    env = {
        **os.environ,
        "PYTHONPATH": str(tree),
        "CKS_MODEL_DIR": str(model_dir),
        "CKS_DATA_DIR": str(data_dir),
        "CKS_PORT": str(port),
    }
    return [sys.executable, "-P", "-m", "service.cli", "serve"], env


def measure(servers: dict[str, Server], requests: Requests, rounds: int, seconds: float) -> dict:
    """Requests/s and server core-ms per request, per (revision, point), in the order measured."""
    for server in servers.values():
        for boxes in (1, 4):
            run_wrk(server.url, requests.scripts[boxes], 4, 2.0)  # warm-up
    runs: dict = {(name, point): [] for name in servers for point in POINTS}
    for round_number in range(rounds):
        for index, (boxes, concurrency) in enumerate(POINTS):
            order = "AB" if (round_number + index) % 2 == 0 else "BA"
            for name in order:
                server = servers[name]
                before = server.cpu_seconds()
                result = run_wrk(server.url, requests.scripts[boxes], concurrency, seconds)
                core_ms = (server.cpu_seconds() - before) * 1e3 / max(result.requests, 1)
                runs[name, (boxes, concurrency)].append((result.requests_per_s, core_ms))
                print(
                    f"round {round_number + 1} {name} {boxes} box(es) c={concurrency:<2}"
                    f" {result.requests_per_s:7.1f} req/s  p50 {result.p50_ms:7.1f} ms"
                    f"  {core_ms:6.2f} core-ms/request"
                    f"  errors {result.errors}  load {os.getloadavg()[0]:.1f}",
                    flush=True,
                )
    return runs


def paced_bodies(sample: Sample) -> dict[str, tuple[str, bytes, str]]:
    """Each paced point's path, body and content type: a 1920x1080 frame's regions, raw (as the
    client sends a numpy frame), with 4 and 1 boxes, and the README's request with 1 box."""
    padding = json.loads((DEFAULT_MODEL_DIR / "manifest.json").read_text())["crop"]["padding"]
    bodies = {}
    for boxes in (4, 1):
        point = make_point(sample, 1920, 1080, boxes)
        files = frame_parts(point.frame, point.parameters, padding, "regions")
        request = httpx.Request("POST", "http://service/v1/predict/frame", files=files)
        name = f"1080p regions, {boxes} box{'es' if boxes > 1 else ''}"
        bodies[name] = ("/v1/predict/frame", request.read(), request.headers["content-type"])
    body, content_type = sample.with_instances(1).multipart_body()
    bodies["README, 1 box"] = ("/v1/predict", body, content_type)
    return bodies


def measure_paced(servers: dict[str, Server], sample: Sample, rounds: int, gap_s: float) -> dict:
    """Median latency (ms) and server core-ms per request, per (revision, paced point): each
    request ``gap_s`` after the previous answer, on a keep-alive connection."""
    bodies = paced_bodies(sample)
    clients = {name: httpx.Client(base_url=server.url, timeout=60) for name, server in servers.items()}
    runs: dict = {(name, point): [] for name in servers for point in bodies}
    try:
        for round_number in range(rounds):
            for index, (point, (path, body, content_type)) in enumerate(bodies.items()):
                for name in "AB" if (round_number + index) % 2 == 0 else "BA":
                    client, server = clients[name], servers[name]
                    client.post(path, content=body, headers={"content-type": content_type})  # warm
                    before, latencies = server.cpu_seconds(), []
                    for _ in range(PACED_REQUESTS):
                        time.sleep(gap_s)
                        started = time.perf_counter()
                        client.post(
                            path, content=body, headers={"content-type": content_type}
                        ).raise_for_status()
                        latencies.append(1e3 * (time.perf_counter() - started))
                    core_ms = (server.cpu_seconds() - before) * 1e3 / PACED_REQUESTS
                    p50 = statistics.median(latencies)
                    runs[name, point].append((p50, core_ms))
                    print(
                        f"round {round_number + 1} {name} {point:<21} paced  p50 {p50:7.2f} ms"
                        f"  {core_ms:6.2f} core-ms/request  load {os.getloadavg()[0]:.1f}",
                        flush=True,
                    )
    finally:
        for client in clients.values():
            client.close()
    return runs


def summary(runs: dict) -> list[str]:
    """Per point: requests/s, then server core-ms per request, each as the medians of A and B and
    the median of the paired ratios B/A [smallest..largest]."""
    lines = [
        "point         req/s: A  B  B/A paired [min..max]     core-ms/request: A  B  B/A paired [min..max]"
    ]
    for boxes, concurrency in POINTS:
        a, b = runs["A", (boxes, concurrency)], runs["B", (boxes, concurrency)]
        lines.append(f"{boxes} box c={concurrency:<2}  {_column(a, b, 0)}    {_column(a, b, 1)}")
    return lines


def paced_summary(runs: dict, gap_ms: float) -> list[str]:
    """Per paced point: the median latency, then server core-ms per request, as ``summary``."""
    lines = [f"paced, {gap_ms:g} ms apart        p50 ms: A  B  B/A paired [min..max]       core-ms/request"]
    for point in dict.fromkeys(point for _, point in runs):
        a, b = runs["A", point], runs["B", point]
        lines.append(f"{point:<22} {_column(a, b, 0)}    {_column(a, b, 1)}")
    return lines


def _column(a: list[tuple[float, float]], b: list[tuple[float, float]], index: int) -> str:
    ratios = [y[index] / x[index] for x, y in zip(a, b, strict=True)]
    medians = [statistics.median(run[index] for run in runs) for runs in (a, b)]
    spread = f"[{min(ratios):.3f}..{max(ratios):.3f}]"
    return f"{medians[0]:8.2f} {medians[1]:8.2f}  {statistics.median(ratios):.3f} {spread}"


def main(argv: list[str] | None = None) -> int:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("a", help="revision A (the reference), e.g. main")
    parser.add_argument("b", help="revision B, e.g. HEAD")
    parser.add_argument("--rounds", type=int, default=6)
    parser.add_argument("--seconds", type=float, default=4.0, help="seconds per point and revision")
    parser.add_argument(
        "--gap-ms", type=float, default=30.0, help="between paced frames (a camera's cadence)"
    )
    parser.add_argument(
        "--model-dir", type=Path, default=DEFAULT_MODEL_DIR, help="the model both serve (default: bundled)"
    )
    args = parser.parse_args(argv)
    require_wrk()
    print(f"A = {args.a}, B = {args.b}; load {os.getloadavg()} on {os.cpu_count()} cores", flush=True)
    with tempfile.TemporaryDirectory(prefix="cks-ab-") as directory, ExitStack() as stack:
        work = Path(directory)
        sample = load_sample()
        requests = Requests.write(work, sample)
        servers = {}
        for name, revision in (("A", args.a), ("B", args.b)):
            tree = export(revision, work / name)
            (work / f"data-{name}").mkdir()
            port = free_port()
            argv_, env = server_argv_env(tree, work / f"data-{name}", port, args.model_dir.resolve())
            servers[name] = stack.enter_context(launch(argv_, env, port, work / f"{name}.log"))
        runs = measure(servers, requests, args.rounds, args.seconds)
        paced = measure_paced(servers, sample, args.rounds, args.gap_ms / 1000)
    lines = ["", *summary(runs), "", *paced_summary(paced, args.gap_ms), f"load at the end {os.getloadavg()}"]
    print("\n".join(lines))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
