"""Requests being computed, counted across real worker processes through the shared file."""

from __future__ import annotations

import multiprocessing
import os
import signal
from multiprocessing.connection import Connection
from pathlib import Path

import numpy as np
import pytest

from service.detector.activity import ACTIVITY_ENV, Activity, share_activity, worker_activity
from service.detector.runtime import Detector
from service.settings import DEFAULT_MODEL_DIR

SPAWN = multiprocessing.get_context("spawn")  # as uvicorn starts its workers


def _worker(commands: Connection) -> None:
    """A worker process: computes (enters) or finishes (leaves) requests when told; answers totals."""
    activity = worker_activity()
    commands.send("ready")
    while (command := commands.recv()) != "stop":
        if command == "enter":
            activity.enter()
        elif command == "leave":
            activity.leave()
        commands.send(activity.total())
    activity.close()


@pytest.fixture
def shared(tmp_path: Path, monkeypatch: pytest.MonkeyPatch) -> Path:
    monkeypatch.delenv(ACTIVITY_ENV, raising=False)  # whatever it was comes back after the test
    return share_activity(tmp_path / "activity")  # sets the variable the spawned workers inherit


class Worker:
    def __init__(self) -> None:
        self.pipe, child = SPAWN.Pipe()
        self.process = SPAWN.Process(target=_worker, args=(child,), daemon=True)
        self.process.start()
        assert self.pipe.recv() == "ready"

    def ask(self, command: str) -> int:
        self.pipe.send(command)
        return self.pipe.recv()

    def stop(self) -> None:
        if self.process.is_alive():
            self.pipe.send("stop")
        self.process.join(timeout=30)


def test_every_worker_sees_the_requests_of_all(shared: Path) -> None:
    workers = [Worker(), Worker()]
    here = worker_activity()  # this process is a third worker
    try:
        assert workers[0].ask("enter") == 1
        assert workers[1].ask("total") == 1, "a request of another worker is counted"
        assert here.total() == 1
        assert workers[1].ask("enter") == 2
        here.enter()
        assert workers[0].ask("total") == 3
        assert workers[0].ask("leave") == 2
        here.leave()
        assert workers[1].ask("leave") == 0
    finally:
        for worker in workers:
            worker.stop()
        here.close()


def test_a_killed_workers_count_goes_with_the_next_worker_to_start(shared: Path) -> None:
    survivor, idle, doomed = Worker(), Worker(), Worker()  # slots 0, 1 and 2
    try:
        doomed.ask("enter")
        assert survivor.ask("enter") == 2
        for worker in (idle, doomed):  # the one mid-request leaves 1 in its slot
            os.kill(worker.process.pid, signal.SIGKILL)
            worker.process.join(timeout=30)
        assert survivor.ask("total") == 2, "a dead worker's count stays until a worker starts"
        replacement = Worker()  # takes slot 1 and zeroes slot 2, as uvicorn's respawned worker does
        try:
            assert replacement.ask("total") == 1, "only the survivor's request is left"
            assert survivor.ask("total") == 1
        finally:
            replacement.stop()
    finally:
        survivor.stop()


def test_a_request_runs_narrow_while_another_worker_computes(shared: Path) -> None:
    other = Worker()
    detector = Detector(DEFAULT_MODEL_DIR, 1, 32, streams=2, solo_threads=2, activity=worker_activity())
    try:
        spec = detector.manifest.input
        batch = np.zeros((4, spec.channels, spec.height, spec.width), dtype=np.float32)
        other.ask("enter")
        with detector.computing():
            detector.run(batch)
        assert detector._ways._estimates == {}, "not alone: no way is timed, the run is an ordinary one"
        other.ask("leave")
        with detector.computing():
            detector.run(batch)
        assert set(detector._ways._estimates[4].seconds) == {True}, "alone again: the wide way is tried"
    finally:
        detector.close()
        other.stop()


def test_one_process_counts_its_own_requests_without_a_shared_file() -> None:
    activity = Activity()
    activity.enter()
    activity.enter()
    assert activity.total() == 2
    activity.leave()
    assert activity.total() == 1
