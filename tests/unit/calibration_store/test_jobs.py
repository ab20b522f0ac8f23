"""Background jobs in the store, on SQLite and PostgreSQL: write, read, prune, share."""

from __future__ import annotations

from datetime import UTC, datetime, timedelta, timezone

import pytest

from calibration_store import (
    CalibrationStore,
    JobExists,
    JobNotFound,
    JobRecord,
    open_store,
)
from tests.unit.calibration_store import rawdb

T0 = datetime(2021, 1, 2, 3, 4, 5, 678901, tzinfo=UTC)


def job(job_id: str = "job-1", created_at: datetime = T0, **fields: object) -> JobRecord:
    fields.setdefault("heartbeat_at", created_at)
    return JobRecord(id=job_id, kind="calibration", owner="host-a:101", created_at=created_at, **fields)


def test_create_update_get(store: CalibrationStore) -> None:
    assert store.get_job("job-1") is None
    created = store.create_job(job(total=12))
    assert created == job(total=12)
    assert store.get_job("job-1") == created

    before = datetime.now(UTC)
    running = store.update_job("job-1", state="running", done=5)
    assert (running.state, running.done, running.total) == ("running", 5, 12)
    assert before <= running.heartbeat_at <= datetime.now(UTC), "a write must refresh the heartbeat"
    assert (running.id, running.kind, running.owner, running.created_at) == (
        "job-1",
        "calibration",
        "host-a:101",
        T0,
    )
    assert store.get_job("job-1") == running

    finished_at = T0 + timedelta(minutes=3)
    done = store.update_job(
        "job-1", state="succeeded", done=12, result={"version": 2}, finished_at=finished_at
    )
    assert (done.state, done.done, done.finished_at) == ("succeeded", 12, finished_at)
    assert done.result == {"version": 2}
    assert done.finished and store.get_job("job-1") == done


def test_update_only_refreshes_the_heartbeat_or_sets_it(store: CalibrationStore) -> None:
    store.create_job(job(state="running", done=3))
    beat = store.update_job("job-1")
    assert beat.heartbeat_at > T0 and (beat.state, beat.done) == ("running", 3)
    old = datetime.now(UTC) - timedelta(hours=1)
    assert store.update_job("job-1", heartbeat_at=old).heartbeat_at == old
    assert store.get_job("job-1").heartbeat_at == old


def test_json_round_trip(store: CalibrationStore) -> None:
    errors = ("image 3 ('ünïcödé \"quoted\".png'): cannot decode", "line\nbreak", "", "😀 emoji")
    result = {"version": 7, "ratio": 0.1 + 0.2, "nested": {"list": [1, None, True, "x"]}, "é": []}
    store.create_job(job(errors=errors, result=result))
    got = store.get_job("job-1")
    assert got.errors == errors and got.result == result
    assert got.result["ratio"] == 0.1 + 0.2  # floats survive exactly
    store.update_job("job-1", errors=[*errors, "more"], result={})
    got = store.get_job("job-1")
    assert got.errors == (*errors, "more") and got.result == {}


def test_timestamps_are_utc_and_exact(store: CalibrationStore) -> None:
    plus_two = T0.astimezone(timezone(timedelta(hours=2)))
    store.create_job(job(created_at=plus_two))
    got = store.get_job("job-1")
    assert got.created_at == T0 and got.created_at.utcoffset() == timedelta(0)
    assert got.heartbeat_at == T0
    assert got.finished_at is None


def test_missing_and_duplicate_jobs(store: CalibrationStore) -> None:
    with pytest.raises(JobNotFound, match="nope"):
        store.update_job("nope", state="running")
    store.create_job(job(total=1))
    with pytest.raises(JobExists, match="job-1"):
        store.create_job(job(total=99, state="failed"))
    assert store.get_job("job-1") == job(total=1)


@pytest.mark.parametrize("bad_id", ["", "nul\x00inside", "line\nbreak", "x" * 201])
def test_impossible_ids(store: CalibrationStore, bad_id: str) -> None:
    assert store.get_job(bad_id) is None
    with pytest.raises(JobNotFound):
        store.update_job(bad_id, state="running")
    with pytest.raises(ValueError, match="job id must be"):
        job(bad_id)


@pytest.mark.parametrize(
    ("fields", "message"),
    [
        ({"state": "paused"}, "job state must be one of"),
        ({"done": -1}, "job done must be >= 0"),
        ({"owner": "someone-else"}, "cannot be changed"),
        ({"id": "other"}, "cannot be changed"),
        ({"heartbeat_at": datetime(2021, 1, 1)}, "timezone-aware"),
        ({"result": {"x": float("nan")}}, "plain JSON"),
    ],
)
def test_updates_are_validated(store: CalibrationStore, fields: dict, message: str) -> None:
    store.create_job(job())
    with pytest.raises(ValueError, match=message):
        store.update_job("job-1", **fields)
    assert store.get_job("job-1") == job()


def test_the_database_refuses_an_unknown_state(store: CalibrationStore, store_url: str) -> None:
    store.create_job(job())
    with pytest.raises(Exception, match="(?i)check"):
        rawdb.query(store_url, "UPDATE calib_jobs SET state = 'paused'")


def test_prune_keeps_the_latest_finished_jobs_and_live_ones(store: CalibrationStore) -> None:
    now = datetime.now(UTC)
    for i in range(6):  # job-0 oldest ... job-5 newest, all finished a moment ago
        store.create_job(job(f"job-{i}", now - timedelta(hours=6 - i), heartbeat_at=now, state="succeeded"))
    # older than all of them but still alive: never pruned by count
    store.create_job(job("live", now - timedelta(days=1), heartbeat_at=now, state="running"))
    assert store.prune_jobs(keep=3) == 3  # finished with 3 newer jobs: job-0, job-1, job-2
    left = {i for i in ("live", *(f"job-{i}" for i in range(6))) if store.get_job(i) is not None}
    assert left == {"live", "job-3", "job-4", "job-5"}
    assert store.prune_jobs(keep=3) == 0
    assert store.prune_jobs(keep=1) == 2  # job-3 and job-4; "live" stays while it is alive


def test_prune_by_age(store: CalibrationStore) -> None:
    now = datetime.now(UTC)
    week = timedelta(days=7)
    store.create_job(
        job(
            "finished-long-ago",
            now - 2 * week,
            heartbeat_at=now - week - timedelta(minutes=1),
            state="failed",
        )
    )
    store.create_job(
        job("dead-long-ago", now - 2 * week, heartbeat_at=now - week - timedelta(minutes=1), state="running")
    )
    store.create_job(
        job(
            "finished-recently",
            now - 2 * week,
            heartbeat_at=now - week + timedelta(minutes=5),
            state="succeeded",
        )
    )
    store.create_job(job("queued", now, heartbeat_at=now))
    assert store.prune_jobs() == 2
    assert store.get_job("finished-long-ago") is None and store.get_job("dead-long-ago") is None
    assert store.get_job("finished-recently") is not None and store.get_job("queued") is not None
    assert store.prune_jobs(max_age=timedelta(days=1)) == 1
    assert store.get_job("queued") is not None


def test_prune_arguments_are_validated(store: CalibrationStore) -> None:
    with pytest.raises(ValueError, match=">= 1"):
        store.prune_jobs(keep=0)
    with pytest.raises(ValueError, match="positive"):
        store.prune_jobs(max_age=timedelta(0))


def test_two_store_objects_see_each_others_jobs(store_url: str) -> None:
    with open_store(store_url) as a, open_store(store_url) as b:
        a.create_job(job("from-a", total=3))
        assert b.get_job("from-a") == a.get_job("from-a")
        b.update_job("from-a", state="running", done=2)
        assert a.get_job("from-a").done == 2
        b.create_job(job("from-b"))
        a.update_job("from-b", state="failed", errors=["boom"], finished_at=T0)
        assert b.get_job("from-b").errors == ("boom",)


def test_stale_jobs_are_the_silent_unfinished_ones(store: CalibrationStore) -> None:
    now = datetime.now(UTC)
    for job_id, silent, state in (
        ("oldest", 300, "running"),
        ("old", 200, "queued"),
        ("fresh", 10, "running"),
        ("finished", 300, "failed"),
    ):
        at = now - timedelta(seconds=silent)
        store.create_job(
            JobRecord(id=job_id, kind="calibration", owner="o", created_at=at, heartbeat_at=at, state=state)
        )
    assert [j.id for j in store.stale_jobs(now - timedelta(seconds=60))] == ["oldest", "old"]
    assert [j.id for j in store.stale_jobs(now - timedelta(seconds=60), limit=1)] == ["oldest"]
    store.update_job("old")  # a sign of life
    assert [j.id for j in store.stale_jobs(now - timedelta(seconds=60))] == ["oldest"]
    with pytest.raises(ValueError, match="timezone-aware"):
        store.stale_jobs(datetime.now())
