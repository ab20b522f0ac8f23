"""The baseline: the bare onnxruntime session, no HTTP, no decode, no scoring.

Run in its own process(es), like the server: ``processes`` copies (CKS_WORKERS), each
with one session built by the service's own ``service.detector.session.create_session``
(CKS_INFERENCE_THREADS intra-op threads) and ``concurrency / processes`` threads each
calling ``session.run`` on the same prebuilt batch of crops, back to back.

    python -m benchmarks.service_bench.raw MODEL_DIR BATCH.npy --threads 1 --concurrency 16
"""

from __future__ import annotations

import argparse
import json
import multiprocessing
import subprocess
import sys
import threading
import time
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from service.detector.manifest import MODEL_FILENAME, load_manifest
from service.detector.session import create_session


@dataclass(frozen=True)
class RawResult:
    """Throughput of bare ``session.run`` calls on one batch of crops."""

    concurrency: int
    batch: int
    runs_per_s: float
    p50_ms: float
    p99_ms: float


def _drive(model_dir: str, threads: int, batch_path: str, concurrency: int, seconds: float) -> list[float]:
    """One process: ``concurrency`` threads running the batch until ``seconds`` have passed."""
    manifest = load_manifest(Path(model_dir))
    session = create_session(Path(model_dir) / MODEL_FILENAME, threads)
    feed = {manifest.input.name: np.load(batch_path)}
    outputs = [manifest.output.name]
    session.run(outputs, feed)  # warm-up
    latencies: list[list[float]] = [[] for _ in range(concurrency)]
    deadline = time.perf_counter() + seconds

    def loop(mine: list[float]) -> None:
        while (start := time.perf_counter()) < deadline:
            session.run(outputs, feed)
            mine.append(time.perf_counter() - start)

    workers = [threading.Thread(target=loop, args=(mine,)) for mine in latencies]
    for worker in workers:
        worker.start()
    for worker in workers:
        worker.join()
    return [value for mine in latencies for value in mine]


def measure(
    model_dir: Path,
    threads: int,
    batch_path: Path,
    concurrency: int,
    seconds: float,
    processes: int = 1,
) -> RawResult:
    """Runs/s of ``concurrency`` callers spread over ``processes`` processes (in this process)."""
    shares = [concurrency // processes + (i < concurrency % processes) for i in range(processes)]
    jobs = [(str(model_dir), threads, str(batch_path), n, seconds) for n in shares if n]
    if len(jobs) == 1:
        latencies = _drive(*jobs[0])
    else:
        with multiprocessing.get_context("spawn").Pool(len(jobs)) as pool:
            latencies = [value for part in pool.starmap(_drive, jobs) for value in part]
    batch = len(np.load(batch_path, mmap_mode="r"))
    p50, p99 = np.percentile(latencies, [50, 99]) * 1e3
    return RawResult(concurrency, batch, len(latencies) / seconds, float(p50), float(p99))


def measure_in_subprocess(
    model_dir: Path,
    threads: int,
    batch_path: Path,
    concurrency: int,
    seconds: float,
    processes: int = 1,
) -> RawResult:
    """``measure`` in a fresh interpreter, so the benchmark's own state does not share its CPU."""
    command = [
        sys.executable,
        "-m",
        "benchmarks.service_bench.raw",
        str(model_dir),
        str(batch_path),
        "--threads",
        str(threads),
        "--concurrency",
        str(concurrency),
        "--seconds",
        str(seconds),
        "--processes",
        str(processes),
    ]
    output = subprocess.run(command, check=True, capture_output=True, text=True).stdout
    return RawResult(**json.loads(output.strip().splitlines()[-1]))


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("model_dir", type=Path)
    parser.add_argument("batch", type=Path, help=".npy of the (N, C, H, W) float32 input batch")
    parser.add_argument("--threads", type=int, default=1, help="intra-op threads (CKS_INFERENCE_THREADS)")
    parser.add_argument("--concurrency", type=int, default=1)
    parser.add_argument("--seconds", type=float, default=5.0)
    parser.add_argument("--processes", type=int, default=1)
    args = parser.parse_args()
    result = measure(args.model_dir, args.threads, args.batch, args.concurrency, args.seconds, args.processes)
    print(json.dumps(result.__dict__))


if __name__ == "__main__":
    main()
