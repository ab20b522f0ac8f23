"""While a lone run computes, lowest-priority threads busy-wait on the other cores; between
runs they sleep; they keep awake only the cores a run may use."""

from __future__ import annotations

import os
import signal
import threading
import time
from collections.abc import Callable, Iterator
from pathlib import Path

import numpy as np
import pytest

from service.detector.session import Detector, usable_cores
from service.infra.keep_awake import KeepAwake, keep_awake, keep_awake_available
from service.infra.settings import DEFAULT_MODEL_DIR

TASKS = Path("/proc/self/task")


def test_the_extension_is_built() -> None:
    assert keep_awake_available(), (
        "service/infra/_keep_awake*.so is missing or was built from older sources: reinstall"
        " (pip install -e .) with a C compiler"
    )


def _awake_threads() -> list[int]:
    return [int(task.name) for task in TASKS.iterdir() if _name(task) == "keep-awake"]


def _name(task: Path) -> str:
    try:
        return (task / "comm").read_text().strip()
    except (FileNotFoundError, ProcessLookupError):  # a thread that ended meanwhile
        return ""


def _state(tid: int) -> str:
    """R (running or runnable), S (sleeping), ... from /proc."""
    return (TASKS / str(tid) / "stat").read_text().rpartition(")")[2].split()[0]


def _blocks_signals(tid: int) -> bool:
    status = (TASKS / str(tid) / "status").read_text()
    blocked = int(next(line for line in status.splitlines() if line.startswith("SigBlk:")).split()[1], 16)
    return all(blocked & (1 << (number - 1)) for number in (signal.SIGINT, signal.SIGTERM, signal.SIGCHLD))


def _soon(condition: Callable[[], bool], what: str) -> None:
    deadline = time.monotonic() + 10
    while not condition():
        assert time.monotonic() < deadline, what
        time.sleep(0.01)


def _all(state: str, at_least: int = 1) -> Callable[[], bool]:
    """Whether ``at_least`` threads are there (each names itself once started), all in ``state``."""
    return lambda: len(_awake_threads()) >= at_least and all(_state(tid) == state for tid in _awake_threads())


def test_the_threads_busy_wait_at_the_lowest_priority_during_a_run_and_sleep_between() -> None:
    awake = KeepAwake(2)
    for _ in range(3):  # again and again, as runs follow each other
        with awake.during():
            _soon(_all("R", at_least=2), "the threads busy-wait while a run holds them")
            assert {os.sched_getscheduler(tid) for tid in _awake_threads()} == {os.SCHED_IDLE}
            assert all(_blocks_signals(tid) for tid in _awake_threads()), "signals are the main thread's"
        _soon(_all("S"), "the threads sleep once the run is over")
        time.sleep(0.05)
        assert _all("S")()


def test_overlapping_runs_keep_the_cores_awake_until_the_last_ends() -> None:
    first, second = KeepAwake(1).during(), KeepAwake(2).during()
    first.__enter__()
    second.__enter__()
    _soon(_all("R"), "busy-waiting for both runs")
    first.__exit__(None, None, None)
    time.sleep(0.05)
    assert _all("R")(), "the second run still computes"
    second.__exit__(None, None, None)
    _soon(_all("S"), "asleep after the last run")


@pytest.fixture
def on_every_core() -> Iterator[int]:
    """The machine's cores (a test worker keeps to one: tests/conftest.py)."""
    kept = os.sched_getaffinity(0)
    os.sched_setaffinity(0, range(os.cpu_count() or 1))
    try:
        yield len(os.sched_getaffinity(0))
    finally:
        os.sched_setaffinity(0, kept)


def test_only_the_other_cores_of_a_run_over_every_core_of_the_process_are_kept_awake(
    on_every_core: int,
) -> None:
    assert on_every_core >= 2, "a machine of 2 or more cores (CI has them)"
    whole = keep_awake(on_every_core)
    assert whole is not None and whole.cores == on_every_core - 1
    assert keep_awake(on_every_core - 1) is None  # fewer threads than cores: which ones is unknown
    assert keep_awake(on_every_core + 1) is None
    assert keep_awake(1) is None


def _states_during(detector: Detector, batch: np.ndarray) -> set[str]:
    """The keep-awake threads' states seen while ``detector`` runs ``batch`` on another thread."""
    seen: set[str] = set()
    running = threading.Thread(target=detector.run, args=(batch,))
    running.start()
    while running.is_alive():
        seen |= {_state(tid) for tid in _awake_threads()}
    return seen


def test_a_lone_run_keeps_the_other_cores_awake_and_a_run_beside_others_does_not(on_every_core: int) -> None:
    assert usable_cores() == on_every_core, "no CPU quota below the machine's cores"
    detector = Detector(DEFAULT_MODEL_DIR, threads=1)
    spec = detector.manifest.input
    batch = np.zeros((32, spec.channels, spec.height, spec.width), np.float32)  # a run of 50-100 ms
    with detector.computing():
        assert "R" in _states_during(detector, batch)
        _soon(_all("S"), "asleep after the run")
        with detector.computing():  # a second request: neither run is alone
            assert _states_during(detector, batch) == {"S"}


def test_a_detector_told_not_to_leaves_the_cores_asleep(on_every_core: int) -> None:
    detector = Detector(DEFAULT_MODEL_DIR, threads=1, keep_cores_awake=False)  # CKS_KEEP_CORES_AWAKE
    spec = detector.manifest.input
    batch = np.zeros((32, spec.channels, spec.height, spec.width), np.float32)
    with KeepAwake(1).during():  # the threads exist (they are started once per process)
        pass
    _soon(_all("S"), "asleep before the run")
    with detector.computing():
        assert _states_during(detector, batch) == {"S"}
