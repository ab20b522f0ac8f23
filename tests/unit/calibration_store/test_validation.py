"""Bad input is refused before touching the database, with a message saying what to fix."""

from __future__ import annotations

from pathlib import Path

import numpy as np
import pytest

from calibration_store import (
    NewVersion,
    ObjectScores,
    ScoreTable,
    SourceBatch,
    open_store,
    sqlite_path,
)
from tests.unit.calibration_store.factories import MODEL_A, new_version, object_scores, score_table

GOOD = np.zeros((2, 3))


def scores(**overrides: object) -> ObjectScores:
    args: dict[str, object] = {
        "object_name": "mug",
        "keypoint_ids": [0, 1, 2],
        "instance_refs": ("a", "b"),
        "scores": {"peak": GOOD, "var": GOOD, "cov": GOOD},
    }
    args.update(overrides)
    return ObjectScores(**args)  # type: ignore[arg-type]


@pytest.mark.parametrize(
    ("overrides", "message"),
    [
        ({"object_name": " "}, "object name"),
        ({"keypoint_ids": []}, "non-empty 1-D"),
        ({"keypoint_ids": [0, 1, 1]}, "duplicates"),
        ({"keypoint_ids": [0, -1, 2]}, "non-negative"),
        ({"keypoint_ids": [0.0, 1.0, 2.0]}, "integers"),
        ({"instance_refs": ()}, "no instances"),
        ({"scores": {}}, "map function names"),
        ({"scores": {"peak": np.zeros((2, 4))}}, r"shape \(2, 3\)"),
        ({"scores": {"peak": np.zeros(6)}}, "shape"),
        ({"scores": {"peak": np.full((2, 3), np.inf)}}, "infinite"),
        ({"scores": {"peak": np.full((2, 3), "x")}}, "real numbers"),
        ({"scores": {"Peak!": GOOD}}, "function name"),
        ({"features": {"gamma": np.full((2, 3), np.nan)}}, "finite for every keypoint"),
        ({"features": {"gamma": np.zeros((3, 3))}}, r"shape \(2, 3\)"),
        ({"features": {"Gamma!": GOOD}}, "feature name"),
        ({"groups": ("camera-1",)}, "1 labels for 2 instances"),
        ({"groups": ("camera-1", "x" * 65)}, "at most 64 characters"),
        ({"groups": ("camera-1", "caf\u00e9")}, "printable ASCII"),
    ],
)
def test_object_scores_validation(overrides: dict[str, object], message: str) -> None:
    with pytest.raises(ValueError, match=message):
        scores(**overrides)


def test_object_scores_normalizes_types() -> None:
    block = scores(
        keypoint_ids=np.array([3, 4, 5], dtype=np.int32), scores={"peak": np.ones((2, 3), dtype=np.float32)}
    )
    assert block.keypoint_ids.dtype == np.int64
    assert block.scores["peak"].dtype == np.float64


def test_score_table_validation() -> None:
    with pytest.raises(ValueError, match="at least one"):
        ScoreTable(())
    with pytest.raises(ValueError, match="unique"):
        ScoreTable((scores(), scores()))
    with pytest.raises(ValueError, match="same functions"):
        ScoreTable((scores(), scores(object_name="cup", scores={"peak": GOOD})))


@pytest.mark.parametrize(
    ("overrides", "error", "message"),
    [
        ({"model_hash": ""}, ValueError, "model hash"),
        ({"model_hash": " abc"}, ValueError, "whitespace"),
        ({"model_name": ""}, ValueError, "model name"),
        ({"author": " "}, ValueError, "author"),
        ({"note": None}, TypeError, "note"),
        ({"parent_version": 0}, ValueError, "parent version"),
        ({"parent_version": True}, TypeError, "parent version"),
        ({"normalization": {"x": float("nan")}}, ValueError, "plain JSON"),
        ({"normalization": {"x": object()}}, ValueError, "plain JSON"),
        ({"normalization": "anchor"}, TypeError, "mapping"),
        ({"source_batches": "b.zip"}, TypeError, "list"),
        ({"source_batches": [{"name": "b"}]}, ValueError, "missing"),
        ({"source_batches": [{"name": "b", "sha256": "xyz", "instances": 1}]}, ValueError, "64 hex"),
        ({"source_batches": [{"name": "b", "sha256": "a" * 64, "instances": -1}]}, ValueError, "instances"),
    ],
)
def test_new_version_validation(overrides: dict[str, object], error: type[Exception], message: str) -> None:
    args: dict[str, object] = {
        "model_hash": MODEL_A,
        "model_name": "m",
        "normalization": {},
        "source_batches": [],
        "author": "alice",
    }
    args.update(overrides)
    with pytest.raises(error, match=message):
        NewVersion(**args)  # type: ignore[arg-type]


def test_source_batch_digest_is_lowercased() -> None:
    assert SourceBatch("b", "A" * 64, 3).sha256 == "a" * 64


def test_store_methods_validate_arguments(tmp_path: Path) -> None:
    with open_store(f"sqlite://{tmp_path}/c.db") as store:
        store.create_version(new_version(), score_table(n=2))
        with pytest.raises(ValueError, match="version number"):
            store.get_version(MODEL_A, 0)
        with pytest.raises(TypeError):
            store.load_scores(MODEL_A, "1")  # type: ignore[arg-type]
        with pytest.raises(ValueError, match="who"):
            store.activate(MODEL_A, 1, who="")
        with pytest.raises(TypeError, match="NewVersion"):
            store.create_version(new_version(), object_scores("mug", 2, [0]))  # type: ignore[arg-type]
        assert store.change_counter() == 1


@pytest.mark.parametrize(
    ("url", "path"),
    [
        ("sqlite:///abs/dir/c.db", "/abs/dir/c.db"),
        ("sqlite:////abs/dir/c.db", "/abs/dir/c.db"),
        ("sqlite:rel/c.db", "rel/c.db"),
        ("sqlite:///abs/with%20space.db", "/abs/with space.db"),
    ],
)
def test_sqlite_urls(url: str, path: str) -> None:
    assert sqlite_path(url) == Path(path)


@pytest.mark.parametrize(
    "url",
    [
        "sqlite://host/c.db",
        "sqlite://",
        "sqlite::memory:",
        "sqlite:///c.db?mode=ro",
        "mysql://x/y",
        "/plain/path.db",
    ],
)
def test_bad_urls(url: str) -> None:
    with pytest.raises(ValueError):
        open_store(url)


def test_sqlite_creates_parent_directories(tmp_path: Path) -> None:
    target = tmp_path / "a" / "b" / "calibration.db"
    open_store(f"sqlite://{target}").close()
    assert target.is_file()
