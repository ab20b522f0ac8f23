"""The store goes away under load and comes back: predictions never wait on it.

A real server (uvicorn on loopback) on a real PostgreSQL cluster of this module's own, so
that stopping it (``pg_ctl stop -m fast``, clients cut off) disturbs no other test. A SQLite store
that stops answering: a real second process holds every WAL lock of the server's database (as one
stuck in a checkpoint or a recovery would), and the service's reads and writes wait on SQLite's own
retries (about 10 s, then "locking protocol"): predictions go on from memory, admin calls get 503.
The scenarios are the ones ``python -m benchmarks.faults_store`` measures (``--fault sqlite-locked``).
"""

from __future__ import annotations

import json
import subprocess
from collections.abc import Iterator
from pathlib import Path

import pytest

from benchmarks.faults_clients import long_batch
from benchmarks.faults_store import run_outage, scene
from calibration_store import open_store
from service.calibration.bundle import bootstrap_default_calibration
from service.calibration.registry import CalibrationRegistry
from service.detector.session import Detector
from service.errors import StoreUnreachable
from service.infra.settings import PACKAGE_ROOT
from tests.live.server import LiveServer, cli, free_port, service_env
from tests.postgres_cluster import PostgresCluster
from tests.samples import model_dir
from tests.service_calls import ADMIN_TOKEN, BUSY_MACHINE_MARGIN_S, assert_problem, wait_until

POLL_S, TIMEOUT_S = 1.0, 1.5  # the store's poll interval and timeout (service.calibration.registry)
#: a poll under way when the store returns may still fail; the next one finds it
TWO_POLLS_S = 2 * (POLL_S + TIMEOUT_S)
#: bounds on waits the behaviour allows, with room for a busy machine: each stays below OUTAGE_S,
#: the wait of a call that waited for the store to come back
WITHIN_TIMEOUT_S = TIMEOUT_S + BUSY_MACHINE_MARGIN_S
WITHIN_TWO_POLLS_S = TWO_POLLS_S + BUSY_MACHINE_MARGIN_S
OUTAGE_S = WITHIN_TIMEOUT_S + 5
#: SQLite's own limit on waiting for a WAL lock, with a margin for a loaded machine
SQLITE_WAL_WAIT_S = 15.0


@pytest.fixture(scope="module")
def cluster() -> Iterator[PostgresCluster]:
    with PostgresCluster.start() as cluster:
        yield cluster


@pytest.mark.slow
def test_predictions_go_on_while_postgresql_is_down(cluster: PostgresCluster, tmp_path: Path) -> None:
    with scene(tmp_path, cluster) as prepared:
        report = run_outage(prepared, outage_s=OUTAGE_S, before_s=2.0, after_s=2.0, clients=1)

    for phase, figures in report.phases.items():
        assert figures.answered > 0 and figures.failed == 0, (phase, figures)
    before, during = report.phases["before"], report.phases["during"]
    # one wait on the store (its timeout) would add TIMEOUT_S to the slowest predictions
    assert during.p99_ms < before.p99_ms + 1000 * TIMEOUT_S, f"predictions waited on the store: {report}"

    ready = report.readyz_during
    assert ready.status == 200, ready
    assert ready.body["active_calibration"] == 1 and ready.body["store"] == "unreachable", ready
    assert "PostgreSQL" in ready.body["store_error"] and ready.body["cache_age_seconds"] > POLL_S, ready

    for admin in (report.admin_first, report.admin_known):  # before and after the server knew
        assert admin.status == 503 and admin.retry_after == "1", admin
        assert admin.body["title"] == "Calibration store unreachable", admin
        assert admin.seconds < WITHIN_TIMEOUT_S, f"an admin call took {admin.seconds:.2f} s to answer 503"
    assert report.admin_known.seconds < TIMEOUT_S, report.admin_known  # no wait once the store is known down
    assert "Predictions keep using the active calibration version 1" in report.admin_known.body["detail"]

    assert report.named_active.status == 200, report.named_active  # in memory
    other = report.named_other
    assert other.status == 503 and other.retry_after == "1" and other.seconds < WITHIN_TIMEOUT_S, other
    for fragment in (
        "calibration version 2 is not in this server's memory",
        "store is unreachable",
        "active version 1, which still answers",
    ):
        assert fragment in other.body["detail"], other.body

    assert report.recovered_after_s < WITHIN_TWO_POLLS_S, report
    assert report.admin_ok_after_s < WITHIN_TWO_POLLS_S, report
    assert report.activation_seen_after_s < WITHIN_TWO_POLLS_S, report


@pytest.mark.slow
def test_a_frozen_postgresql_answers_admin_calls_503_within_the_store_timeout(
    cluster: PostgresCluster, tmp_path: Path
) -> None:
    """SIGSTOP on the cluster: an admin read sent before the server knew waits on a connection
    that neither fails nor answers, until the store's watchdog cuts it (1.5 s);
    before, it waited for the SIGCONT. Predictions go on; after the SIGCONT the service recovers."""
    with scene(tmp_path, cluster) as prepared:
        report = run_outage(prepared, outage_s=OUTAGE_S, before_s=1.0, after_s=1.0, clients=1, fault="freeze")

    for phase, figures in report.phases.items():
        assert figures.answered > 0 and figures.failed == 0, (phase, figures)
    first, known = report.admin_first, report.admin_known
    assert first.status == 503 and first.retry_after == "1", first
    assert first.body["title"] == "Calibration store unreachable", first
    took = first.seconds
    assert took < WITHIN_TIMEOUT_S + TIMEOUT_S, f"an admin call took {took:.2f} s to answer 503"
    assert known.status == 503 and known.seconds < TIMEOUT_S, known
    assert report.recovered_after_s < WITHIN_TWO_POLLS_S, report
    assert report.admin_ok_after_s < WITHIN_TWO_POLLS_S, report
    assert report.activation_seen_after_s < WITHIN_TWO_POLLS_S, report


def finished(server: LiveServer, job_id: str) -> bool:
    response = server.client.get(f"/v1/admin/jobs/{job_id}", headers=server.admin)
    return response.status_code == 200 and response.json()["state"] in ("succeeded", "failed", "interrupted")


@pytest.mark.slow
def test_a_job_caught_by_the_outage_fails_cleanly_and_the_next_one_succeeds(
    cluster: PostgresCluster, tmp_path: Path, samples_dir: Path, coco: dict
) -> None:
    body = long_batch(4)
    with scene(tmp_path, cluster) as prepared:
        server = prepared.server
        response = server.upload(body)
        assert response.status_code == 202, response.text
        job_id = response.json()["id"]
        cluster.stop_server()  # while the job scores, long before it writes its version
        try:
            wait_until(
                lambda: f"job {job_id}: its final state is not stored yet" in server.log(),
                "the job gave up writing its final state for now",
                timeout=120,
            )
        finally:
            cluster.start_server()
        wait_until(lambda: server.client.get("/readyz").json()["store"] == "ok", "the store is back", 30)
        # The runner's writer lands the final state. Right after the restart a busy machine (load
        # average 20+) took more than the store's timeout to hand out a fresh connection, and a job
        # read got 503: that is not what this test is about.
        wait_until(lambda: finished(server, job_id), "the job's final state is stored", timeout=60)
        job = server.job(job_id)
        assert job["state"] == "failed", job
        assert "the calibration store was unreachable" in job["errors"][0], job
        assert "nothing was stored: upload the batch again" in job["errors"][0], job
        assert "internal error" not in json.dumps(job)
        assert server.versions() == [1, 2]
        assert server.calibrate(body)["result"]["version"] == 3


@pytest.mark.slow
def test_serve_refuses_to_start_without_the_store(cluster: PostgresCluster, tmp_path: Path) -> None:
    url = cluster.create_database()
    env = service_env(tmp_path / "data", store_url=url, port=free_port())
    cluster.stop_server()
    try:
        result = subprocess.run(
            [*cli(), "serve"], env=env, cwd=PACKAGE_ROOT, capture_output=True, text=True, timeout=90
        )
    finally:
        cluster.start_server()
    assert result.returncode == 1, result.stderr  # the store or the system, not the command (test_cli_errors)
    last = result.stderr.strip().splitlines()[-1]
    assert last.startswith("error: the calibration store postgresql://"), last
    assert "cannot connect to PostgreSQL" in last, last
    assert "Traceback" not in result.stderr


def test_a_frozen_database_is_reported_unreachable_and_the_cache_answers(cluster: PostgresCluster) -> None:
    """SIGSTOP: connections neither fail nor answer; the store's watchdog cuts a connection that
    has not answered within its timeout, so the poll fails (before, it hung, and only the rule
    for polls hanging past twice the timeout said the store was away)."""
    detector = Detector(model_dir())
    with open_store(cluster.create_database(), timeout_s=0.5) as store:
        bootstrap_default_calibration(store, detector, model_dir())
        registry = CalibrationRegistry(store, detector.model_hash, detector.manifest, 0.2, 0.5)
        assert registry.start() == 1
        try:
            cluster.freeze_server()
            try:
                wait_until(lambda: not registry.health().reachable, "the frozen store is reported")
                error = registry.health().error
                assert "PostgreSQL" in error and "has not answered a poll" not in error, error
                assert registry.resolve(None) == 1  # from memory, no wait
                assert registry.thresholds(1, "cov", "keypoint", 0.1, None).values.size
                with pytest.raises(StoreUnreachable, match="Predictions keep using the active calibration"):
                    registry.require_store()
            finally:
                cluster.thaw_server()
            wait_until(lambda: registry.health().reachable, "the thawed store answers again", 2 * 0.2 + 1.0)
        finally:
            registry.stop()


@pytest.mark.slow
def test_refusals_of_a_store_outage_reach_the_audit_trail_after_a_stop(
    cluster: PostgresCluster, tmp_path: Path
) -> None:
    """PostgreSQL stopped: an activation and an upload are refused (503) by the store check
    before their routes run. The server is stopped before the store returns; a new server on the
    same data directory appends both refusals (kept in the stopped one's outbox) once it is back."""
    url = cluster.create_database()
    data = tmp_path / "data"
    with LiveServer(data, admin_token=ADMIN_TOKEN, store_url=url) as server:
        cluster.stop_server()
        try:
            wait_until(lambda: server.client.get("/readyz").json()["store"] == "unreachable", "store away")
            reason = {"reason": "during the outage"}
            activation = server.client.post(
                "/v1/admin/calibrations/1/activate", json=reason, headers=server.admin
            )
            assert_problem(activation, 503, "store is unreachable")
            assert_problem(server.upload(long_batch(1)), 503, "store is unreachable")
        except BaseException:
            cluster.start_server()
            raise
    outboxes = list((data / "audit-outbox").glob("*.jsonl"))
    assert len(outboxes) == 1 and len(outboxes[0].read_text().splitlines()) == 2, outboxes
    cluster.start_server()

    with LiveServer(data, admin_token=ADMIN_TOKEN, store_url=url) as server:

        def refusals() -> list[dict]:
            entries = server.client.get("/v1/admin/audit", headers=server.admin).json()["entries"]
            return [e for e in entries if (e["action"], e["outcome"]) == ("admin", "refused")]

        wait_until(lambda: len(refusals()) == 2, "both refusals are in the audit trail", timeout=15)
        paths = sorted(entry["details"]["path"] for entry in refusals())
        assert paths == ["/v1/admin/calibrations", "/v1/admin/calibrations/1/activate"], refusals()
        for entry in refusals():
            assert entry["details"]["status"] == 503 and "happened_at" in entry["details"], entry
            assert entry["who"] == "admin", entry
        wait_until(lambda: not list((data / "audit-outbox").glob("*.jsonl")), "the outbox is emptied")


@pytest.mark.slow
def test_a_locked_sqlite_store_answers_admin_503_and_predictions_go_on(tmp_path: Path) -> None:
    with scene(tmp_path, None) as prepared:
        report = run_outage(
            prepared, outage_s=2.0, before_s=1.0, after_s=1.0, clients=1, fault="sqlite-locked"
        )

    for phase, figures in report.phases.items():
        assert figures.answered > 0 and figures.failed == 0, (phase, figures)
    first, known = report.admin_first, report.admin_known
    for admin in (first, known):  # sent before the server knew, and after
        assert admin.status == 503 and admin.retry_after == "1", admin
        assert admin.body["title"] == "Calibration store unreachable", admin
    assert first.seconds < SQLITE_WAL_WAIT_S, first
    assert known.seconds < TIMEOUT_S, known  # the hung poll said the store is away: no wait
    assert "the store has not answered a poll" in report.readyz_during.body["store_error"], report
    assert report.named_active.status == 200 and report.named_other.status == 503, report
    two_polls = 2 * (POLL_S + TIMEOUT_S) + BUSY_MACHINE_MARGIN_S
    assert report.recovered_after_s < two_polls and report.admin_ok_after_s < two_polls, report
    assert report.activation_seen_after_s < two_polls, report
