"""Several processes on one store, on both backends (tests/conftest.py store_url): writers creating
and activating versions at once get distinct gap-free numbers; of writers storing the same content,
one version; of concurrent bootstraps, one winner; jobs written at once are all read; concurrent
first opens and upgrades migrate once; a writer killed with SIGKILL mid-transaction leaves no trace
of its version. The children are spawned (no inherited state); their functions are workers.py's.
"""

from __future__ import annotations

import hashlib
import multiprocessing
import os
import signal
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

import pytest

from calibration_store import open_store, sqlite_path
from calibration_store.migrations import SQLITE_MIGRATIONS
from tests.unit.calibration_store import rawdb
from tests.unit.calibration_store.factories import (
    MODEL_A,
    MODEL_B,
    assert_tables_identical,
    new_version,
    score_table,
)
from tests.unit.calibration_store.test_migrations import open_with_schema_1
from tests.unit.calibration_store.workers import (
    bootstrap,
    create_and_activate,
    create_same_content,
    open_concurrently,
    run_jobs,
    write_then_hang,
)

CONTEXT = multiprocessing.get_context("spawn")
WORKERS = 4
ROUNDS = 6
CONTENT_WRITERS = 6
KEY = hashlib.sha256(b"the same instances").hexdigest()
LATEST = SQLITE_MIGRATIONS[-1].version
LARGE = 150_000  # 150k instances x 8 keypoints x 3 functions = 29 MB of scores


def run_together(
    target: Callable[..., None], args_for: Sequence[tuple[Any, ...]], timeout: float = 60
) -> list[Any]:
    """Run target(*args, barrier, ..., results) in len(args_for) processes; collect results.

    Each args tuple gets the shared barrier inserted after its first element (the URL)
    and the result queue appended.
    """
    barrier = CONTEXT.Barrier(len(args_for))
    results = CONTEXT.Queue()
    procs = [CONTEXT.Process(target=target, args=(args[0], barrier, *args[1:], results)) for args in args_for]
    for proc in procs:
        proc.start()
    collected = [results.get(timeout=timeout) for _ in procs]
    for proc in procs:
        proc.join(timeout=timeout)
        assert proc.exitcode == 0, f"worker exited with {proc.exitcode}"
    return collected


def test_concurrent_writers_get_distinct_gap_free_numbers(store_url: str) -> None:
    open_store(store_url).close()  # schema in place before the race (opens race elsewhere)
    results = run_together(create_and_activate, [(store_url, w, ROUNDS) for w in range(WORKERS)])
    created = [item for _, made, _ in results for item in made]
    activated = [item for _, _, acts in results for item in acts]
    with open_store(store_url) as store:
        for model in (MODEL_A, MODEL_B):
            numbers = sorted(n for m, n in created if m == model)
            assert numbers == list(range(1, len(numbers) + 1)), "duplicate or missing numbers"
            assert [v.number for v in store.list_versions(model)] == numbers
            log = store.activation_log(model)
            assert sorted((a.seq, a.version) for a in log) == sorted(
                (seq, version) for m, seq, version in activated if m == model
            )
            assert [a.seq for a in log] == sorted(a.seq for a in log)
            assert store.active_version(model) == log[-1]
        assert store.change_counter() == 2 * WORKERS * ROUNDS


def test_writers_in_several_processes_store_one_version(store_url: str) -> None:
    open_store(store_url).close()  # schema in place before the race
    results = run_together(create_same_content, [(store_url, w, KEY) for w in range(CONTENT_WRITERS)])
    stored = [number for _, outcome, number in results if outcome == "stored"]
    refused = [number for _, outcome, number in results if outcome == "refused"]
    assert len(stored) == 1 and refused == [stored[0]] * (CONTENT_WRITERS - 1), results
    with open_store(store_url) as store:
        assert [v.number for v in store.list_versions(MODEL_A)] == stored == [1]


def test_exactly_one_of_several_concurrent_bootstraps_wins(store_url: str) -> None:
    open_store(store_url).close()  # schema in place before the race
    results = run_together(bootstrap, [(store_url, w) for w in range(WORKERS)])
    winners = [worker for worker, number in results if number is not None]
    assert len(winners) == 1 and sorted(n for _, n in results if n is not None) == [1]
    with open_store(store_url) as store:
        (version,) = store.list_versions(MODEL_A)
        assert version.number == 1 and version.author == f"w{winners[0]}"
        active = store.active_version(MODEL_A)
        assert active.version == 1 and active.who == f"w{winners[0]}"
        assert len(store.activation_log(MODEL_A)) == 1


def test_processes_share_jobs(store_url: str) -> None:
    """Two processes write jobs at the same time; a third object reads all of them."""
    reports = run_together(run_jobs, [(store_url, worker, 10) for worker in range(2)])
    with open_store(store_url) as store:
        for worker, ids in reports:
            for i, job_id in enumerate(ids):
                got = store.get_job(job_id)
                assert got is not None, job_id
                assert (got.state, got.done, got.total, got.result) == ("succeeded", 5, 5, {"i": i})
                assert got.owner == f"worker-{worker}"


def test_concurrent_first_opens_migrate_once(store_url: str) -> None:
    seen = run_together(open_concurrently, [(store_url,)] * 4)
    assert seen == [list(range(1, LATEST + 1))] * 4


def test_concurrent_upgrades_of_an_old_database_migrate_once(
    store_url: str, monkeypatch: pytest.MonkeyPatch
) -> None:
    open_with_schema_1(store_url, monkeypatch).close()
    seen = run_together(open_concurrently, [(store_url,)] * 4)
    assert seen == [list(range(1, LATEST + 1))] * 4
    with open_store(store_url) as store:
        assert store.get_job("none") is None


def _wait_for(path: Path, proc: object, timeout: float = 60) -> None:
    deadline = time.monotonic() + timeout
    while not path.exists():
        assert proc.is_alive(), f"writer died early with exit code {proc.exitcode}"
        assert time.monotonic() < deadline, "writer never reached the middle of its transaction"
        time.sleep(0.02)


def _assert_write_in_flight(url: str) -> None:
    """The kill really lands mid-write: uncommitted data exists on the server or on disk."""
    if url.startswith("sqlite:"):
        wal = sqlite_path(url).with_name(sqlite_path(url).name + "-wal")
        assert wal.stat().st_size > 10_000_000, "expected uncommitted pages spilled to the WAL"
    else:
        rows = rawdb.query(
            url,
            "SELECT count(*) FROM pg_stat_activity"
            " WHERE state = 'idle in transaction' AND datname = current_database()",
        )
        assert rows[0][0] == 1


def _kill_writer_mid_transaction(url: str, tmp_path: Path) -> None:
    ready = tmp_path / "writer-is-mid-transaction"
    proc = CONTEXT.Process(target=write_then_hang, args=(url, str(ready), LARGE))
    proc.start()
    try:
        _wait_for(ready, proc)
        _assert_write_in_flight(url)
        os.kill(proc.pid, signal.SIGKILL)
    finally:
        proc.join(timeout=30)
    assert proc.exitcode == -signal.SIGKILL


def test_sigkill_mid_write_leaves_nothing_partial(store_url: str, tmp_path: Path) -> None:
    kept = score_table(n=30)
    with open_store(store_url) as store:
        store.create_version(new_version(), kept)
        store.activate(MODEL_A, 1, who="alice")
        counter = store.change_counter()

    _kill_writer_mid_transaction(store_url, tmp_path)

    with open_store(store_url) as store:
        store.ping()
        assert [v.number for v in store.list_versions(MODEL_A)] == [1]
        assert store.change_counter() == counter
        assert store.active_version(MODEL_A).version == 1
        assert_tables_identical(store.load_scores(MODEL_A, 1), kept)
        # the killed writer's number is not lost: numbering stays gap-free
        assert store.create_version(new_version(), score_table(n=3)).number == 2
