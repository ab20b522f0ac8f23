"""A real fleet (issue 36): three replicas behind Debian's HAProxy on one real PostgreSQL, under
steady predict load through the Python client (an idempotent call retried once). No request is
lost while one replica is SIGKILLed and another drained with SIGTERM; an activation through the
proxy reaches every replica within the store's poll interval (with a margin for a loaded
machine); the drift answer read from each replica directly is the same. The scenario:
``benchmarks.fleet.run_fleet`` (docs/deploy.md)."""

from __future__ import annotations

from pathlib import Path

import pytest

from benchmarks.fleet import POLL_S, REPLICAS, haproxy_binary, run_fleet
from tests.postgres_cluster import PostgresCluster


@pytest.mark.slow
def test_a_fleet_behind_haproxy_loses_no_request(postgres_cluster: PostgresCluster, tmp_path: Path) -> None:
    assert haproxy_binary(), "HAProxy is not installed: apt-get install haproxy (.ci/run does)"
    report = run_fleet(tmp_path, postgres_cluster)

    lost = {phase: [o for o in outcomes if o != "answered"] for phase, outcomes in report.outcomes.items()}
    assert not any(lost.values()), report.outcomes
    for phase in ("steady", "activation", "one replica SIGKILLed", "one replica drained (SIGTERM)"):
        assert report.outcomes[phase]["answered"] > 0, (phase, report.outcomes)
    assert report.drained_exit == 0, report.drained_exit
    assert max(report.activation_spread_s) < 3 * POLL_S + 2, report.activation_spread_s
    keys = ("replicas", "frames", "recorded", "independent_looks", "alarm")
    answers = {tuple(d[k] for k in keys) for d in report.drift}
    assert len(answers) == 1, report.drift  # the same answer, whichever replica is asked
    (answer,) = answers
    assert answer[0] == REPLICAS and answer[2] > 0, answer
