"""Functions run in child processes (multiprocessing 'spawn') by the store tests."""

from __future__ import annotations

import time
from pathlib import Path
from typing import Any

from calibration_store import open_store
from calibration_store.sqlstore import EncodedBlock, SqlStore
from tests.unit.calibration_store import rawdb
from tests.unit.calibration_store.factories import MODEL_A, MODEL_B, large_table, new_version, score_table


def write_then_hang(url: str, ready_file: str, n_instances: int) -> None:
    """Start writing a large version, say so through ready_file, then wait to be killed."""
    original = SqlStore._insert_block

    def insert_and_hang(self: SqlStore, cur: Any, version_id: int, block: EncodedBlock) -> None:
        original(self, cur, version_id, block)
        Path(ready_file).write_text(str(version_id))
        time.sleep(600)

    SqlStore._insert_block = insert_and_hang  # type: ignore[method-assign]
    store = open_store(url)
    store.create_version(new_version(note="never committed"), large_table(n_instances))


def create_and_activate(url: str, barrier: Any, worker: int, rounds: int, results: Any) -> None:
    """Create `rounds` versions alternating two models, activating each; report them."""
    store = open_store(url)
    barrier.wait(timeout=60)
    created, activated = [], []
    for i in range(rounds):
        model = MODEL_A if (worker + i) % 2 == 0 else MODEL_B
        info = store.create_version(new_version(model, author=f"w{worker}"), score_table(n=4))
        created.append((model, info.number))
        activation = store.activate(model, info.number, who=f"w{worker}", reason=str(i))
        activated.append((model, activation.seq, activation.version))
    store.close()
    results.put((worker, created, activated))


def open_concurrently(url: str, barrier: Any, results: Any) -> None:
    """Open the store at the same moment as the other workers; report the schema rows."""
    barrier.wait(timeout=60)
    with open_store(url) as store:
        store.ping()
    results.put(rawdb.schema_versions(url))


def run_jobs(url: str, barrier: Any, worker: int, count: int, results: Any) -> None:
    """Create `count` jobs and take each through running to succeeded; report their ids."""
    from datetime import UTC, datetime

    from calibration_store import JobRecord

    store = open_store(url)
    barrier.wait(timeout=60)
    ids = []
    for i in range(count):
        now = datetime.now(UTC)
        job_id = f"w{worker}-{i}"
        store.create_job(
            JobRecord(
                id=job_id, kind="test", owner=f"worker-{worker}", created_at=now, heartbeat_at=now, total=5
            )
        )
        store.update_job(job_id, state="running")
        for done in range(1, 6):
            store.update_job(job_id, done=done)
        store.update_job(job_id, state="succeeded", result={"i": i}, finished_at=datetime.now(UTC))
        ids.append(job_id)
    store.close()
    results.put((worker, ids))


def bootstrap(url: str, barrier: Any, worker: int, results: Any) -> None:
    """Try to store the first version of MODEL_A at the same moment as the other workers."""
    store = open_store(url)
    barrier.wait(timeout=60)
    info = store.create_first_version(new_version(author=f"w{worker}"), score_table(n=4), who=f"w{worker}")
    store.close()
    results.put((worker, None if info is None else info.number))


def create_same_content(url: str, barrier: Any, worker: int, key: str, results: Any) -> None:
    """Store a version with content ``key`` at the same moment as the other workers; report the
    number, or the number of the version the store named as its twin."""
    from dataclasses import replace

    from calibration_store import DuplicateVersion

    store = open_store(url)
    barrier.wait(timeout=60)
    try:
        info = store.create_version(
            replace(new_version(author=f"w{worker}"), content_key=key), score_table(n=4)
        )
        results.put((worker, "stored", info.number))
    except DuplicateVersion as error:
        results.put((worker, "refused", error.number))
    finally:
        store.close()
