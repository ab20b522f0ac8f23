"""A SQLite store that stops answering: predictions go on from memory, admin calls get 503.

A real server on its SQLite file, and a real second process holding every WAL lock of that
database (as one stuck in a checkpoint or a recovery would): the service's reads and writes
wait on SQLite's own retries (about 10 s, then "locking protocol"). The scenario:
``benchmarks.faults_store.run_outage`` with ``fault="sqlite-locked"``.
"""

from __future__ import annotations

from pathlib import Path

import pytest

from benchmarks.faults_store import run_outage, scene
from tests.service_calls import BUSY_MACHINE_MARGIN_S

POLL_S, TIMEOUT_S = 1.0, 1.5  # the defaults of CKS_STORE_POLL_SECONDS, CKS_STORE_TIMEOUT_SECONDS
#: SQLite's own limit on waiting for a WAL lock, with a margin for a loaded machine
SQLITE_WAL_WAIT_S = 15.0


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
