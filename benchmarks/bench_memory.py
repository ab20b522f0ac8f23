"""Memory under load: the server's resident memory after 1,000 and after 100,000 predict requests.

    python -m benchmarks.bench_memory                    # 100,000 requests: ~8-10 min with wrk
    python -m benchmarks.bench_memory --requests 20000   # shorter
    CKS_WORKERS=2 python -m benchmarks.bench_memory      # any CKS_* setting applies to the server

A real ``keypoint-service serve`` process (its workers too) on a loopback port answers the
README's request (a 640x480 JPEG, 1 box, multipart) at concurrency 16; VmRSS of the whole
process tree (``/proc/<pid>/status``) is read after ``--first`` requests and then every
``--every`` requests up to ``--requests``. The goal (issue 19): RSS after the last reading
within 5% of RSS after the first. The load is wrk (``apt-get install -y wrk``) when installed,
otherwise a light client of this process's threads (``--load python``).
"""

from __future__ import annotations

import argparse
import itertools
import os
import shutil
import sys
import tempfile
import threading
import time
from pathlib import Path

import httpx

from benchmarks.service_bench.inputs import load_sample
from benchmarks.service_bench.loadgen import post_requests
from benchmarks.service_bench.machine import this_machine
from benchmarks.service_bench.report import MEMORY_GOAL
from benchmarks.service_bench.runs import Memory
from benchmarks.service_bench.server import serve
from service.infra.settings import Settings

Body = tuple[bytes, str]  # (request body, content type)


def post_with_threads(url: str, body: Body, count: int, concurrency: int) -> tuple[int, int]:
    """``count`` predicts from ``concurrency`` keep-alive connections: (requests, non-2xx or failed)."""
    content, content_type = body
    tickets, failures = itertools.count(), itertools.count()
    headers = {"Content-Type": content_type, "Accept": "application/json"}

    def client_loop() -> None:
        with httpx.Client(base_url=url, timeout=60, headers=headers) as client:
            while next(tickets) < count:
                try:
                    ok = client.post("/v1/predict", content=content).is_success
                except httpx.HTTPError:
                    ok = False
                if not ok:
                    next(failures)

    threads = [threading.Thread(target=client_loop) for _ in range(concurrency)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    return count, next(failures)


def send(url: str, body: Body, count: int, concurrency: int, load: str) -> tuple[int, int]:
    """``count`` requests with the chosen load generator: (requests answered, errors)."""
    if load == "wrk":
        result = post_requests(url, *body, count, concurrency)
        return result.requests, result.errors
    return post_with_threads(url, body, count, concurrency)


def checkpoints(first: int, every: int, total: int) -> list[int]:
    """Request counts to read RSS at: ``first``, then every ``every``, ending at ``total``."""
    marks = [first, *range(every, total, every)]
    return sorted({mark for mark in marks if first <= mark < total} | {total})


def measure(args: argparse.Namespace, body: Body, log_path: Path) -> Memory:
    model_dir = str(Path(Settings().model.directory).resolve())
    memory, done = Memory(), 0
    with serve({"CKS_MODEL_DIR": model_dir}, log=log_path) as server:
        for mark in checkpoints(args.first, args.every, args.requests):
            started = time.perf_counter()
            answered, errors = send(server.url, body, mark - done, args.concurrency, args.load)
            seconds = time.perf_counter() - started
            done += answered
            memory.after.append((done, server.rss_kib()))
            print(
                f"after {done:>7} requests: VmRSS {memory.after[-1][1] / 1024:7.1f} MiB"
                f"  ({answered / seconds:5.0f} req/s, {errors} errors)",
                flush=True,
            )
    return memory


def verdict(memory: Memory) -> str:
    (first, _), (last, _) = memory.after[0], memory.after[-1]
    met = "met" if abs(memory.growth) <= MEMORY_GOAL else "NOT met"
    return (
        f"RSS after {last} requests / after {first}: {1 + memory.growth:.3f} ({memory.growth:+.1%});"
        f" goal within {MEMORY_GOAL:.0%}: {met}"
    )


def parse_args(argv: list[str] | None) -> argparse.Namespace:
    parser = argparse.ArgumentParser(
        prog="python -m benchmarks.bench_memory",
        description=__doc__,
        formatter_class=argparse.RawDescriptionHelpFormatter,
    )
    parser.add_argument("--requests", type=int, default=100_000, help="requests in all (default 100000)")
    parser.add_argument("--first", type=int, default=1_000, help="the baseline reading (default 1000)")
    parser.add_argument("--every", type=int, default=10_000, help="read RSS every N requests (default 10000)")
    parser.add_argument("--concurrency", type=int, default=16, help="connections (default 16)")
    parser.add_argument("--instances", type=int, default=1, help="boxes per request (default 1)")
    parser.add_argument("--load", choices=["wrk", "python"], help="default: wrk when installed, else python")
    parser.add_argument("--log", type=Path, help="the server's log (default: a file in the temp folder)")
    args = parser.parse_args(argv)
    if not 0 < args.first < args.requests:
        parser.error("--first must be above 0 and below --requests")
    if args.every <= 0 or args.concurrency <= 0 or args.instances <= 0:
        parser.error("--every, --concurrency and --instances must be above 0")
    args.load = args.load or ("wrk" if shutil.which("wrk") else "python")
    return args


def server_settings() -> str:
    """The CKS_* variables the server inherits (secrets masked)."""
    secret = ("CKS_STORE_URL", "CKS_ADMIN_TOKEN")
    ours = sorted((k, v) for k, v in os.environ.items() if k.startswith("CKS_"))
    return " ".join(f"{k}={'***' if k in secret else v}" for k, v in ours) or "defaults"


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    samples = Path(Settings().model.directory).resolve() / "samples"
    sample = load_sample(samples).with_instances(args.instances)
    log_path = args.log or Path(tempfile.gettempdir()) / f"bench-memory-server-{os.getpid()}.log"
    print(f"machine: {this_machine().describe()}")
    print(f"server: keypoint-service serve, settings: {server_settings()}; log: {log_path}")
    print(f"load: {args.load}, concurrency {args.concurrency}, {args.instances} box(es) a request, multipart")
    memory = measure(args, sample.multipart_body(), log_path)
    print(verdict(memory))
    return 0


if __name__ == "__main__":
    sys.exit(main())
