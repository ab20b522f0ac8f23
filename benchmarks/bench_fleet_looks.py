"""What counting a fleet's looks once costs (service/monitoring/fleet_looks.py): the share's size
and its encode and decode times with a full frame log, and the time to decide the undecided looks
of several replicas (every drift evaluation of a fleet does, while looks are recent).

Run: python -m benchmarks.bench_fleet_looks   (crafted frames of 4 instances, the bundled
model's 48 keypoints with full windows of 500 rows; best of 3 timings).
"""

from __future__ import annotations

import argparse
import time
from collections.abc import Callable

import numpy as np

from service.monitoring.drift_monitor import SHARED_FRAMES
from service.monitoring.drift_shares import decode_share, encode_share
from service.monitoring.fleet_looks import COUNTED, ReplicaLooks, fleet_statuses
from service.monitoring.looks import Frame

OBJECTS = ("duck", "mug", "lego", "bunny")
CHANNELS, WINDOW, COLUMNS = 48, 500, 7


def replica(rng: np.random.Generator, name: str, frames: int, looks: int, undecided: int) -> ReplicaLooks:
    """``frames`` frames over 15 s (three intervals), ``looks`` of them first frames of looks."""
    times = np.sort(rng.uniform(0.0, 15.0, frames))
    shown = tuple(Frame(OBJECTS, rng.uniform(0.0, 600.0, (len(OBJECTS), 4))) for _ in times)
    starts = np.sort(rng.choice(times, looks, replace=False))
    statuses = np.full(looks, COUNTED)
    statuses[looks - undecided :] = np.nan
    keys = rng.integers(-(2**62), 2**62, looks)
    return ReplicaLooks(
        name, 15.0, 0.0, times, shown, np.column_stack([starts, rng.normal(size=looks)]), statuses, keys
    )


def best_seconds(action: Callable[[], object], repeats: int = 3) -> float:
    timings = []
    for _ in range(repeats):
        started = time.perf_counter()
        action()
        timings.append(time.perf_counter() - started)
    return min(timings)


def main(argv: list[str] | None = None) -> dict[str, float]:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--replicas", type=int, default=3)
    parser.add_argument("--frames", type=int, default=SHARED_FRAMES, help="frames in each replica's log")
    parser.add_argument("--looks", type=int, default=1000, help="looks each replica shares")
    parser.add_argument("--undecided", type=int, nargs="+", default=[100, 1000], help="undecided looks each")
    arguments = parser.parse_args(argv)
    rng = np.random.default_rng(0)
    figures = {}
    for undecided in arguments.undecided:
        fleet = [
            replica(rng, f"r{n}", arguments.frames, arguments.looks, undecided)
            for n in range(arguments.replicas)
        ]
        seconds = best_seconds(lambda fleet=fleet: fleet_statuses(fleet))
        figures[f"decide {undecided}"] = seconds
        print(
            f"deciding {undecided} undecided looks of each of {arguments.replicas} replicas"
            f" ({arguments.frames} frames each): {seconds * 1e3:.0f} ms"
        )
    windows = [np.zeros((WINDOW, COLUMNS)) for _ in range(CHANNELS)]
    seen = replica(rng, "r0", arguments.frames, arguments.looks, 0)
    payload = encode_share(1, arguments.frames, CHANNELS * WINDOW, windows, windows, seen)
    bare = encode_share(1, 0, CHANNELS * WINDOW, windows, windows, replica(rng, "r0", 0, 0, 0))
    figures["encode"] = best_seconds(lambda: encode_share(1, 0, 0, windows, windows, seen))
    figures["decode"] = best_seconds(lambda: decode_share("r0", 0.0, payload))
    figures["megabytes"], figures["megabytes without frames"] = len(payload) / 1e6, len(bare) / 1e6
    print(
        f"share with full windows: {len(payload) / 1e6:.2f} MB with {arguments.frames} frames and"
        f" {arguments.looks} looks ({len(bare) / 1e6:.2f} MB without), encode"
        f" {figures['encode'] * 1e3:.0f} ms, decode {figures['decode'] * 1e3:.0f} ms"
    )
    return figures


if __name__ == "__main__":
    main()
