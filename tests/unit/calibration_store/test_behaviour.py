"""The behavioural contract of CalibrationStore, run on SQLite and PostgreSQL alike."""

from __future__ import annotations

import struct
import threading
from datetime import UTC, datetime, timedelta

import numpy as np
import pytest

from calibration_store import (
    CalibrationStore,
    ObjectScores,
    ScoreTable,
    StoreError,
    VersionNotFound,
    open_store,
)
from tests.unit.calibration_store import rawdb
from tests.unit.calibration_store.factories import (
    MODEL_A,
    MODEL_B,
    assert_tables_identical,
    new_version,
    score_table,
)


def test_empty_store(store: CalibrationStore) -> None:
    store.ping()
    assert store.list_versions(MODEL_A) == []
    assert store.active_version(MODEL_A) is None
    assert store.activation_log(MODEL_A) == []
    assert store.change_counter() == 0
    with pytest.raises(VersionNotFound):
        store.get_version(MODEL_A, 1)
    with pytest.raises(VersionNotFound):
        store.load_scores(MODEL_A, 1)


def test_create_returns_stored_metadata(store: CalibrationStore) -> None:
    before = datetime.now(UTC)
    info = store.create_version(new_version(note="first upload"), score_table(n=20))
    assert info.number == 1
    assert info.model_hash == MODEL_A
    assert info.model_name == "hourglass-test"
    assert info.normalization == {"mode": "anchor", "top_k": 100}
    assert [b.as_dict() for b in info.source_batches] == [new_version().source_batches[0].as_dict()]
    assert (info.author, info.note, info.parent_version) == ("alice", "first upload", None)
    assert info.created_at.tzinfo is not None and info.created_at.utcoffset() == timedelta(0)
    assert before - timedelta(seconds=1) <= info.created_at <= datetime.now(UTC)
    assert info.n_instances == 30
    assert dict(info.object_counts) == {"mug": 20, "bottle": 10}
    assert info.functions == ("cov", "peak", "var")
    assert store.get_version(MODEL_A, 1) == info
    assert store.list_versions(MODEL_A) == [info]


def test_numbers_are_per_model_and_consecutive(store: CalibrationStore) -> None:
    numbers = [
        store.create_version(new_version(model), score_table(n=3)).number
        for model in (MODEL_A, MODEL_A, MODEL_B, MODEL_A, MODEL_B)
    ]
    assert numbers == [1, 2, 1, 3, 2]
    assert [v.number for v in store.list_versions(MODEL_A)] == [1, 2, 3]
    assert [v.number for v in store.list_versions(MODEL_B)] == [1, 2]


def test_scores_round_trip_bit_exact(store: CalibrationStore) -> None:
    table = score_table(n=50, seed=3)
    special = np.array(
        [
            struct.unpack("<d", struct.pack("<Q", 0x7FF8_0000_0000_0001))[0],  # NaN payload
            -0.0,
            5e-324,
            np.finfo(np.float64).max,
            -1.5,
            np.nan,
        ]
    ).reshape(1, 6)
    odd = ObjectScores(
        "plate", [11, 12, 13, 14, 15, 16], ("ünïcode ref",), {f: special for f in ("peak", "var", "cov")}
    )
    table = ScoreTable((*table.objects, odd))
    info = store.create_version(new_version(), table)
    loaded = store.load_scores(MODEL_A, info.number)
    assert_tables_identical(loaded, table)
    matrix = loaded.object("plate").scores["peak"]
    assert matrix.dtype == np.float64
    assert not matrix.flags.writeable


def test_parent_version_must_exist(store: CalibrationStore) -> None:
    store.create_version(new_version(), score_table(n=2))
    with pytest.raises(VersionNotFound):
        store.create_version(new_version(parent=7), score_table(n=2))
    child = store.create_version(new_version(parent=1), score_table(n=2))
    assert (child.number, child.parent_version) == (2, 1)
    assert store.change_counter() == 2


def test_activation_log_and_rollback(store: CalibrationStore) -> None:
    for _ in range(3):
        store.create_version(new_version(), score_table(n=2))
    first = store.activate(MODEL_A, 2, who="alice", reason="first")
    second = store.activate(MODEL_A, 3, who="bob", reason="better")
    rollback = store.activate(MODEL_A, 2, who="carol", reason="rollback")
    assert store.active_version(MODEL_A) == rollback
    assert store.activation_log(MODEL_A) == [first, second, rollback]
    assert [a.version for a in store.activation_log(MODEL_A)] == [2, 3, 2]
    assert first.seq < second.seq < rollback.seq
    assert (rollback.who, rollback.reason) == ("carol", "rollback")
    assert first.activated_at <= second.activated_at <= rollback.activated_at
    assert store.active_version(MODEL_B) is None


def test_activating_a_missing_version_changes_nothing(store: CalibrationStore) -> None:
    store.create_version(new_version(), score_table(n=2))
    counter = store.change_counter()
    with pytest.raises(VersionNotFound):
        store.activate(MODEL_A, 2, who="alice")
    with pytest.raises(VersionNotFound):
        store.activate(MODEL_B, 1, who="alice")
    assert store.activation_log(MODEL_A) == []
    assert store.change_counter() == counter


def test_change_counter_tracks_writes_only(store: CalibrationStore) -> None:
    seen = [store.change_counter()]
    store.create_version(new_version(), score_table(n=2))
    seen.append(store.change_counter())
    store.list_versions(MODEL_A)
    store.load_scores(MODEL_A, 1)
    seen.append(store.change_counter())
    store.activate(MODEL_A, 1, who="alice")
    seen.append(store.change_counter())
    assert seen == [0, 1, 1, 2]


def test_other_replica_sees_changes(store_url: str) -> None:
    with open_store(store_url) as writer, open_store(store_url) as reader:
        start = reader.change_counter()
        writer.create_version(new_version(), score_table(n=2))
        writer.activate(MODEL_A, 1, who="alice")
        assert reader.change_counter() == start + 2
        assert reader.active_version(MODEL_A) == writer.active_version(MODEL_A)


def test_data_survives_reopen(store_url: str) -> None:
    table = score_table(n=10)
    with open_store(store_url) as store:
        store.create_version(new_version(), table)
        store.activate(MODEL_A, 1, who="alice")
    with open_store(store_url) as store:
        assert store.active_version(MODEL_A).version == 1
        assert_tables_identical(store.load_scores(MODEL_A, 1), table)


def test_history_is_immutable_in_the_database(store: CalibrationStore, store_url: str) -> None:
    store.create_version(new_version(), score_table(n=2))
    store.activate(MODEL_A, 1, who="alice")
    for sql in (
        "UPDATE calib_versions SET note = 'edited'",
        "DELETE FROM calib_score_arrays",
        "DELETE FROM calib_feature_arrays",
        "DELETE FROM calib_activations",
    ):
        with pytest.raises(Exception, match="immutable"):
            rawdb.query(store_url, sql)
    assert store.get_version(MODEL_A, 1).note == ""


def test_threads_share_one_store(store: CalibrationStore) -> None:
    errors: list[BaseException] = []

    def work(seed: int) -> None:
        try:
            for _ in range(3):
                info = store.create_version(new_version(), score_table(n=5, seed=seed))
                store.load_scores(MODEL_A, info.number)
                store.activate(MODEL_A, info.number, who=f"thread{seed}")
        except BaseException as exc:  # reported below
            errors.append(exc)

    threads = [threading.Thread(target=work, args=(i,)) for i in range(6)]
    for thread in threads:
        thread.start()
    for thread in threads:
        thread.join()
    assert errors == []
    assert [v.number for v in store.list_versions(MODEL_A)] == list(range(1, 19))
    assert len(store.activation_log(MODEL_A)) == 18
    assert store.change_counter() == 36


def test_closed_store_refuses_use(store_url: str) -> None:
    store = open_store(store_url)
    store.close()
    with pytest.raises(StoreError):
        store.list_versions(MODEL_A)
