"""The in-process limit: what the service's own functions cost per request without any server.

Core-ms per request = the CPU time of the process per request while the stage breakdown runs
with one intra-op thread (every stage on the calling thread: CPU time, not wall time, so other
jobs on the machine do not inflate it); the limit at many clients is cores / core-ms. The
latency bound for one client is the smallest wall-clock total over the thread settings (one
intra-op thread, or one per core).
"""

from __future__ import annotations

import os
import time
from dataclasses import dataclass
from pathlib import Path

from benchmarks.service_bench.breakdown import service_state, stage_breakdown
from benchmarks.service_bench.inputs import Sample


@dataclass(frozen=True)
class Limit:
    boxes: int
    core_ms: float  # CPU time per request, one intra-op thread
    best_latency_ms: float  # smallest total over the thread settings
    best_threads: int
    stages: dict[str, float]  # one intra-op thread

    @property
    def requests_per_s(self) -> float:
        return cores() * 1e3 / self.core_ms


def cores() -> int:
    return len(os.sched_getaffinity(0))


def in_process_limits(
    model_dir: Path, sample: Sample, boxes: tuple[int, ...], iterations: int
) -> list[Limit]:
    """One ``Limit`` per box count, the stages timed with one intra-op thread and with one per core."""
    totals: dict[int, dict[int, dict[str, float]]] = {}
    core_ms: dict[int, float] = {}
    for threads in sorted({1, cores()}):
        with service_state(model_dir, threads) as state:
            totals[threads] = {}
            for n in boxes:
                started = time.process_time()
                totals[threads][n] = stage_breakdown(state, sample.with_instances(n), iterations)
                if threads == 1:  # iterations plus the warm-up
                    core_ms[n] = (time.process_time() - started) * 1e3 / (iterations + 1)
    limits = []
    for n in boxes:
        best = min(totals, key=lambda t: totals[t][n]["total"])
        limits.append(Limit(n, core_ms[n], totals[best][n]["total"], best, totals[1][n]))
    return limits
