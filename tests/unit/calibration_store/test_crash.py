"""A writer killed with SIGKILL mid-transaction leaves no trace of its version."""

from __future__ import annotations

import os
import signal
import time
from pathlib import Path

from calibration_store import open_store, sqlite_path
from tests.unit.calibration_store import rawdb
from tests.unit.calibration_store.factories import MODEL_A, assert_tables_identical, new_version, score_table
from tests.unit.calibration_store.processes import CONTEXT
from tests.unit.calibration_store.workers import write_then_hang

LARGE = 150_000  # 150k instances x 8 keypoints x 3 functions = 29 MB of scores


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
