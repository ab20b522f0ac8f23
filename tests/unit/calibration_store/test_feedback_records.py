"""Retained predictions, their labels and adaptive state, on both backends (SQLite and PostgreSQL)."""

from __future__ import annotations

from datetime import UTC, datetime, timedelta

from calibration_store import (
    AdaptiveState,
    CalibrationStore,
    LabelOutcome,
    LabelVerdicts,
    NewAuditEntry,
    RetainedPrediction,
)

MODEL = "f" * 64


def retained(prediction_id: str, at: datetime, age: timedelta = timedelta(days=1)) -> RetainedPrediction:
    record = {"rows": [{"peak": [1.5, 2.5], "threshold": None, "covariance": [[0.1, 1e-17], [1e-17, 3.0]]}]}
    return RetainedPrediction(prediction_id, MODEL, 1, "cam-1", at, at + age, record)


def entry(prediction_id: str) -> NewAuditEntry:
    return NewAuditEntry(MODEL, "robot", "feedback", "labelled", version=1, details={"id": prediction_id})


def test_a_retained_prediction_is_labelled_once_with_its_audit_entry(store: CalibrationStore) -> None:
    now = datetime.now(UTC)
    store.retain_predictions([retained("a", now)], max_rows=10)
    kept = store.retained_prediction("a")
    assert kept is not None and kept.labels is None and kept.stream == "cam-1"
    assert kept.record["rows"][0]["covariance"][0][1] == 1e-17  # floats kept bit for bit
    labels = {"rows": [{"row": 0, "covered": True}]}
    assert store.label_prediction("a", labels, "robot", now, entry("a")) is LabelOutcome.LABELLED
    assert store.label_prediction("a", labels, "robot", now, entry("a")) is LabelOutcome.ALREADY_LABELLED
    assert store.label_prediction("b", labels, "robot", now, entry("b")) is LabelOutcome.MISSING
    labelled = store.labelled_predictions(MODEL, limit=10)
    assert [p.id for p in labelled] == ["a"] and labelled[0].labels == labels
    assert labelled[0].labelled_by == "robot"
    feedback = [e for e in store.audit_log(MODEL) if e.action == "feedback"]
    assert len(feedback) == 1 and feedback[0].details == {"id": "a"}


def test_expired_rows_take_no_label_and_are_removed(store: CalibrationStore) -> None:
    now = datetime.now(UTC)
    store.retain_predictions([retained("old", now - timedelta(hours=2), timedelta(hours=1))], max_rows=10)
    later = now + timedelta(seconds=1)
    assert store.label_prediction("old", {}, "robot", later, entry("old")) is LabelOutcome.MISSING
    assert not [e for e in store.audit_log(MODEL) if e.action == "feedback"]
    store.retain_predictions([retained("new", now)], max_rows=10)
    assert store.retained_prediction("old") is None and store.retained_prediction("new") is not None


def test_the_oldest_rows_go_first_beyond_the_size_bound(store: CalibrationStore) -> None:
    now = datetime.now(UTC)
    store.retain_predictions([retained("p0", now)], max_rows=3)
    later = [retained(f"p{i}", now + timedelta(seconds=i)) for i in range(1, 5)]
    store.retain_predictions(later, max_rows=3)  # one batch
    kept = [i for i in range(5) if store.retained_prediction(f"p{i}") is not None]
    assert kept == [2, 3, 4]
    assert store.oldest_retained() == now + timedelta(seconds=2)


def test_adaptive_state_is_compare_and_set(store: CalibrationStore) -> None:
    assert store.adaptive_state("k") is None
    assert store.save_adaptive_state("k", 0, AdaptiveState("k", 1, {"alpha": 0.1}))
    assert not store.save_adaptive_state("k", 0, AdaptiveState("k", 1, {"alpha": 0.2}))  # another writer won
    assert store.save_adaptive_state("k", 1, AdaptiveState("k", 2, {"alpha": 0.095}))
    assert not store.save_adaptive_state("k", 1, AdaptiveState("k", 2, {"alpha": 0.3}))
    state = store.adaptive_state("k")
    assert state is not None and state.steps == 2 and state.state == {"alpha": 0.095}


def test_new_labels_are_read_by_id_in_label_order(store: CalibrationStore) -> None:
    now = datetime.now(UTC)
    store.retain_predictions([retained(name, now) for name in ("a", "b", "c", "d")], max_rows=10)
    labels = {"rows": [{"row": 0, "covered": False}]}
    for name, seconds in (("c", 1), ("a", 2), ("b", 2)):  # d stays unlabelled
        at = now + timedelta(seconds=seconds)
        assert store.label_prediction(name, labels, "robot", at, entry(name)) is LabelOutcome.LABELLED
    assert store.labelled_since(MODEL, None) == [
        ("c", now + timedelta(seconds=1)),
        ("a", now + timedelta(seconds=2)),
        ("b", now + timedelta(seconds=2)),
    ]
    assert [i for i, _ in store.labelled_since(MODEL, now + timedelta(seconds=2))] == ["a", "b"]
    assert store.labelled_since("e" * 64, None) == []
    found = store.retained_predictions(["b", "c", "gone"])
    assert sorted(p.id for p in found) == ["b", "c"] and all(p.labels == labels for p in found)
    many = [f"x{i}" for i in range(1200)]  # more ids than one query takes
    assert {p.id for p in store.retained_predictions([*many, "a"])} == {"a"}


def test_a_labels_verdicts_are_stored_with_it_and_go_with_its_prediction(store: CalibrationStore) -> None:
    now = datetime.now(UTC)
    store.retain_predictions([retained(name, now) for name in ("a", "b", "c")], max_rows=10)
    verdicts = LabelVerdicts('{"groups":[["version","all",[[0, 2]]]]}', {"look": "a", "covered": [1]})
    labels = {"rows": [{"row": 0, "covered": True}]}
    assert store.label_prediction("a", labels, "robot", now, entry("a"), verdicts) is LabelOutcome.LABELLED
    assert (
        store.label_prediction("b", labels, "robot", now, entry("b")) is LabelOutcome.LABELLED
    )  # none given
    refused = LabelVerdicts("{}", {"look": "refused"})
    assert (
        store.label_prediction("a", labels, "robot", now, entry("a"), refused)
        is LabelOutcome.ALREADY_LABELLED
    )
    assert store.label_prediction("z", labels, "robot", now, entry("z"), refused) is LabelOutcome.MISSING
    many = [f"x{i}" for i in range(1200)]  # more ids than one query takes
    assert store.label_verdicts([*many, "a", "b", "c", "z"]) == {"a": verdicts}
    later = [retained(f"p{i}", now + timedelta(seconds=i)) for i in range(1, 11)]
    store.retain_predictions(later, max_rows=10)  # a, b and c are evicted, a's verdicts with it
    assert store.retained_prediction("a") is None and store.label_verdicts(["a"]) == {}
