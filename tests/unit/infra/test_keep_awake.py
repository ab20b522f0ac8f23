"""While a lone run computes, lowest-priority threads busy-wait on the other cores; between
runs they sleep; they keep awake only the cores a run may use."""

from __future__ import annotations

import os
import threading
import time
from collections.abc import Callable, Iterator

import numpy as np
import pytest

from service.detector.session import Detector, usable_cores
from service.infra.keep_awake import KeepAwake, glibc_spin_lock, keep_awake
from service.infra.settings import DEFAULT_MODEL_DIR


def _state(thread: threading.Thread) -> str:
    """R (running or runnable), S (sleeping), ... from /proc."""
    stat = f"/proc/self/task/{thread.native_id}/stat"
    with open(stat) as file:
        return file.read().rpartition(")")[2].split()[0]


def _soon(condition: Callable[[], bool], what: str) -> None:
    deadline = time.monotonic() + 10
    while not condition():
        assert time.monotonic() < deadline, what
        time.sleep(0.01)


def _all_in(threads: list[threading.Thread], state: str) -> Callable[[], bool]:
    return lambda: bool(threads) and all(_state(thread) == state for thread in threads)


@pytest.fixture
def awake() -> KeepAwake:
    spin_lock = glibc_spin_lock()
    assert spin_lock is not None, "glibc's pthread spin locks (Linux)"
    return KeepAwake(2, spin_lock)


def test_the_threads_busy_wait_at_the_lowest_priority_while_held_and_sleep_between(awake: KeepAwake) -> None:
    for _ in range(3):  # again and again, as runs follow each other
        with awake.during():
            _soon(_all_in(awake.threads, "R"), "the threads busy-wait while the run holds them")
            assert len(awake.threads) == 2
            assert {os.sched_getscheduler(thread.native_id) for thread in awake.threads} == {os.SCHED_IDLE}
        _soon(_all_in(awake.threads, "S"), "the threads sleep once the run is over")
        time.sleep(0.05)
        assert _all_in(awake.threads, "S")()


def test_overlapping_runs_keep_the_cores_awake_until_the_last_ends(awake: KeepAwake) -> None:
    first, second = awake.during(), awake.during()
    first.__enter__()
    second.__enter__()
    _soon(_all_in(awake.threads, "R"), "busy-waiting for both runs")
    first.__exit__(None, None, None)
    time.sleep(0.05)
    assert _all_in(awake.threads, "R")(), "the second run still computes"
    second.__exit__(None, None, None)
    _soon(_all_in(awake.threads, "S"), "asleep after the last run")


@pytest.fixture
def on_every_core() -> Iterator[int]:
    """The machine's cores (a test worker keeps to one: tests/conftest.py)."""
    kept = os.sched_getaffinity(0)
    os.sched_setaffinity(0, range(os.cpu_count() or 1))
    try:
        yield len(os.sched_getaffinity(0))
    finally:
        os.sched_setaffinity(0, kept)


def test_only_the_cores_of_a_run_over_every_core_of_the_process_are_kept_awake(on_every_core: int) -> None:
    assert on_every_core >= 2, "a machine of 2 or more cores (CI has them)"
    shared = keep_awake(on_every_core)
    assert shared is not None and shared is keep_awake(on_every_core)  # one per process
    assert keep_awake(on_every_core - 1) is None  # a run on fewer cores than the process may use
    assert keep_awake(on_every_core + 1) is None
    assert keep_awake(1) is None


def _states_during(detector: Detector, batch: np.ndarray, threads: list[threading.Thread]) -> set[str]:
    """The keep-awake threads' states seen while ``detector`` runs ``batch`` on another thread."""
    seen: set[str] = set()
    running = threading.Thread(target=detector.run, args=(batch,))
    running.start()
    while running.is_alive():
        seen |= {_state(thread) for thread in threads}
    return seen


def test_a_lone_run_keeps_the_other_cores_awake_and_a_run_beside_others_does_not(on_every_core: int) -> None:
    assert usable_cores() == on_every_core, "no CPU quota below the machine's cores"
    detector = Detector(DEFAULT_MODEL_DIR, threads=1)
    shared = keep_awake(on_every_core)
    assert shared is not None
    spec = detector.manifest.input
    batch = np.zeros((32, spec.channels, spec.height, spec.width), np.float32)  # a run of 50-100 ms
    with detector.computing():
        detector.run(batch[:1])
        assert len(shared.threads) == on_every_core - 1
        assert {os.sched_getscheduler(thread.native_id) for thread in shared.threads} == {os.SCHED_IDLE}
        assert "R" in _states_during(detector, batch, shared.threads)
        _soon(_all_in(shared.threads, "S"), "asleep after the run")
        with detector.computing():  # a second request: neither run is alone
            assert _states_during(detector, batch, shared.threads) == {"S"}
