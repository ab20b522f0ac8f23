"""A paired A/B of two revisions on the README's request: does a mechanism earn its place?

    python -m benchmarks.bench_ab main HEAD                  # ~4 min: 6 rounds, 4 s a point
    python -m benchmarks.bench_ab main my-branch --rounds 12 --seconds 3

Each revision is exported (``git archive``, with this tree's built C kernel copied in) and served
with its defaults (``keypoint-service serve``, the bundled model), both servers up side by side
and loaded one at a time: POST /v1/predict, multipart, the sample image with 1 and 4 boxes, at
concurrency 1 and 16 (wrk). Rounds alternate which revision goes first. Prints every run, then
per point the medians and the median of the paired ratios B/A with their spread, requests/s and
server core-ms per request; and the load average, which a shared machine's figures depend on.
"""

from __future__ import annotations

import argparse
import os
import shutil
import statistics
import subprocess
import sys
import tempfile
from contextlib import ExitStack
from pathlib import Path

from benchmarks.peers.measure import Requests
from benchmarks.service_bench.inputs import load_sample
from benchmarks.service_bench.loadgen import require_wrk, run_wrk
from benchmarks.service_bench.server import Server, free_port, launch
from service.infra.settings import DEFAULT_MODEL_DIR

ROOT = Path(__file__).resolve().parents[1]
POINTS = [(boxes, concurrency) for boxes in (1, 4) for concurrency in (1, 16)]


def export(revision: str, directory: Path) -> Path:
    """``revision``'s tracked files in ``directory``, with this tree's built extensions (untracked;
    a revision that does not import one leaves it unused)."""
    directory.mkdir()
    archive = subprocess.run(["git", "-C", str(ROOT), "archive", revision], check=True, capture_output=True)
    subprocess.run(["tar", "-x", "-C", str(directory)], input=archive.stdout, check=True)
    for extension in (ROOT / "service").rglob("_*.so"):
        shutil.copy(extension, directory / extension.relative_to(ROOT))
    return directory


def server_argv_env(tree: Path, data_dir: Path, port: int) -> tuple[list[str], dict[str, str]]:
    """How to serve ``tree``'s code (``-P``: not the working directory's) with the bundled model."""
    env = {
        **os.environ,
        "PYTHONPATH": str(tree),
        "CKS_MODEL_DIR": str(DEFAULT_MODEL_DIR),
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
    args = parser.parse_args(argv)
    require_wrk()
    print(f"A = {args.a}, B = {args.b}; load {os.getloadavg()} on {os.cpu_count()} cores", flush=True)
    with tempfile.TemporaryDirectory(prefix="cks-ab-") as directory, ExitStack() as stack:
        work = Path(directory)
        requests = Requests.write(work, load_sample(DEFAULT_MODEL_DIR / "samples"))
        servers = {}
        for name, revision in (("A", args.a), ("B", args.b)):
            tree = export(revision, work / name)
            (work / f"data-{name}").mkdir()
            port = free_port()
            argv_, env = server_argv_env(tree, work / f"data-{name}", port)
            servers[name] = stack.enter_context(launch(argv_, env, port, work / f"{name}.log"))
        runs = measure(servers, requests, args.rounds, args.seconds)
    print("\n".join(["", *summary(runs), f"load at the end {os.getloadavg()}"]))
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
