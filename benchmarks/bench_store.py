"""Round trip (write + read) of one calibration version of 100 000 instances.

    python -m benchmarks.bench_store                         # SQLite in a temp dir
    python -m benchmarks.bench_store --postgres URL          # also an existing PostgreSQL
    python -m benchmarks.bench_store --throwaway-postgres    # also a temporary cluster
    (or set CALIBRATION_STORE_BENCH_POSTGRES_URL)

Prints seconds per write, read and round trip (best and median of --repeat runs).
Goal: a SQLite round trip under 1 s.
"""

from __future__ import annotations

import argparse
import os
import statistics
import tempfile
import time
from collections.abc import Callable
from contextlib import ExitStack
from pathlib import Path
from typing import TypeVar

import numpy as np

from calibration_store import NewVersion, ObjectScores, ScoreTable, open_store

MODEL_HASH = "b" * 64
KEYPOINTS = 8
FUNCTIONS = ("peak", "var", "cov")
T = TypeVar("T")


def build_table(n_instances: int, n_objects: int = 2, seed: int = 0) -> ScoreTable:
    """n_instances split over n_objects, KEYPOINTS each, 10% NaN (unlabeled)."""
    rng = np.random.default_rng(seed)
    blocks = []
    for index, n in enumerate(np.array_split(np.arange(n_instances), n_objects)):
        size = len(n)
        scores = {}
        for function in FUNCTIONS:
            matrix = rng.gamma(2.0, 1.0, size=(size, KEYPOINTS))
            matrix[rng.random(matrix.shape) < 0.1] = np.nan
            scores[function] = matrix
        refs = tuple(f"batch.zip:{i}:{i}" for i in range(size))
        ids = np.arange(KEYPOINTS) + index * KEYPOINTS
        blocks.append(ObjectScores(f"object{index}", ids, refs, scores))
    return ScoreTable(tuple(blocks))


def new_version() -> NewVersion:
    batch = {"name": "batch.zip", "sha256": "c" * 64, "instances": 100_000}
    return NewVersion(MODEL_HASH, "bench", {"mode": "anchor"}, [batch], author="bench")


def timed(action: Callable[..., T], *args: object) -> tuple[float, T]:
    start = time.perf_counter()
    result = action(*args)
    return time.perf_counter() - start, result


def bench(url: str, table: ScoreTable, repeat: int) -> dict[str, list[float]]:
    runs: dict[str, list[float]] = {"write": [], "read": [], "round trip": []}
    with open_store(url) as store:
        for _ in range(repeat):
            write, info = timed(store.create_version, new_version(), table)
            read, _ = timed(store.load_scores, MODEL_HASH, info.number)
            runs["write"].append(write)
            runs["read"].append(read)
            runs["round trip"].append(write + read)
    return runs


def report(name: str, runs: dict[str, list[float]], table: ScoreTable) -> None:
    megabytes = table.n_instances * KEYPOINTS * len(FUNCTIONS) * 8 / 1e6
    print(
        f"{name}: {table.n_instances} instances x {KEYPOINTS} keypoints x "
        f"{len(FUNCTIONS)} functions ({megabytes:.1f} MB of float64)"
    )
    for label, values in runs.items():
        print(f"  {label:<10} best {min(values):.3f} s   median {statistics.median(values):.3f} s")


def parse_args() -> argparse.Namespace:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--instances", type=int, default=100_000)
    parser.add_argument("--repeat", type=int, default=5)
    parser.add_argument("--postgres", default=os.environ.get("CALIBRATION_STORE_BENCH_POSTGRES_URL"))
    parser.add_argument(
        "--throwaway-postgres",
        action="store_true",
        help="start a temporary cluster (needs the PostgreSQL server binaries)",
    )
    return parser.parse_args()


def main() -> None:
    args = parse_args()
    table = build_table(args.instances)
    with ExitStack() as stack:
        directory = Path(stack.enter_context(tempfile.TemporaryDirectory()))
        report("SQLite", bench(f"sqlite://{directory}/bench.db", table, args.repeat), table)
        postgres = args.postgres
        if args.throwaway_postgres and not postgres:
            from tests.postgres_cluster import PostgresCluster

            cluster = stack.enter_context(PostgresCluster.start())
            postgres = cluster.create_database("bench")
        if postgres:
            report("PostgreSQL", bench(postgres, table, args.repeat), table)


if __name__ == "__main__":
    main()
