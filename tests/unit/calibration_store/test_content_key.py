"""One version per content key: a rule of the store, whatever the number of writers at once."""

from __future__ import annotations

import hashlib
from dataclasses import replace
from datetime import UTC, datetime

import pytest

from calibration_store import (
    ActivationIntent,
    CalibrationStore,
    DuplicateVersion,
    JobCompletion,
    JobRecord,
    NewAuditEntry,
)
from tests.unit.calibration_store import rawdb
from tests.unit.calibration_store.factories import MODEL_A, MODEL_B, new_version, score_table

KEY = hashlib.sha256(b"the same instances").hexdigest()
OTHER = hashlib.sha256(b"other instances").hexdigest()


def keyed(key: str | None, model: str = MODEL_A):
    return replace(new_version(model), content_key=key)


def test_a_second_version_with_the_same_key_is_refused_and_writes_nothing(store: CalibrationStore) -> None:
    first = store.create_version(keyed(KEY), score_table(n=4))
    counter = store.change_counter()
    now = datetime.now(UTC)
    store.create_job(JobRecord(id="twin", kind="calibration", owner="w", created_at=now, heartbeat_at=now))
    entry = NewAuditEntry(model_hash=MODEL_A, who="bob", action="calibration", outcome="stored")
    with pytest.raises(DuplicateVersion) as refused:
        store.create_version(
            keyed(KEY),
            score_table(n=4),
            activation=ActivationIntent("bob", "twin"),
            job=JobCompletion("twin", {}),
            audit=[entry],
        )
    assert (refused.value.number, refused.value.model_hash) == (first.number, MODEL_A)
    assert [v.number for v in store.list_versions(MODEL_A)] == [first.number]
    assert store.change_counter() == counter and store.active_version(MODEL_A) is None
    assert store.get_job("twin").state == "queued" and store.audit_log(MODEL_A) == []
    # the number the refusal used is not lost: numbers stay gap-free
    assert store.create_version(keyed(OTHER), score_table(n=4)).number == first.number + 1


def test_the_rule_is_per_model_and_none_is_no_rule(store: CalibrationStore) -> None:
    assert store.create_version(keyed(KEY), score_table(n=4)).number == 1
    assert store.create_version(keyed(KEY, MODEL_B), score_table(n=4)).number == 1
    assert [store.create_version(keyed(None), score_table(n=4)).number for _ in range(2)] == [2, 3]


def test_a_key_must_be_a_digest() -> None:
    with pytest.raises(ValueError, match="content key must be a sha256 hex digest"):
        keyed("not a digest")


def test_the_database_holds_the_rule_without_the_store(store: CalibrationStore, store_url: str) -> None:
    """The unique index refuses a second row with the key even from a writer that skips the check."""
    store.create_version(keyed(KEY), score_table(n=4))
    with pytest.raises(Exception, match="(?i)unique"):
        rawdb.query(
            store_url,
            "INSERT INTO calib_versions (model_hash, number, model_name, normalization, source_batches,"
            " author, note, created_at, n_instances, object_counts, functions, content_key)"
            f" VALUES ('{MODEL_A}', 99, 'm', '{{}}', '[]', 'a', '', '2026-01-01T00:00:00+00:00', 4, '{{}}',"
            f" '[]', '{KEY}')",
        )
