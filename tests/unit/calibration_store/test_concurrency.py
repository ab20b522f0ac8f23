"""Several processes creating and activating versions at once, on both backends."""

from __future__ import annotations

from calibration_store import open_store
from tests.unit.calibration_store.factories import MODEL_A, MODEL_B
from tests.unit.calibration_store.processes import run_together
from tests.unit.calibration_store.workers import create_and_activate

WORKERS = 4
ROUNDS = 6


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
