"""Builders of sample versions and score tables for the store tests."""

from __future__ import annotations

import hashlib

import numpy as np

from calibration_store import NewVersion, ObjectScores, ScoreTable

MODEL_A = hashlib.sha256(b"model a").hexdigest()
MODEL_B = hashlib.sha256(b"model b").hexdigest()
FUNCTIONS = ("peak", "var", "cov")


def batch(name: str = "batch-1.zip", instances: int = 10) -> dict[str, object]:
    return {"name": name, "sha256": hashlib.sha256(name.encode()).hexdigest(), "instances": instances}


def new_version(
    model_hash: str = MODEL_A, parent: int | None = None, note: str = "", author: str = "alice"
) -> NewVersion:
    return NewVersion(
        model_hash=model_hash,
        model_name="hourglass-test",
        normalization={"mode": "anchor", "top_k": 100},
        source_batches=[batch()],
        author=author,
        note=note,
        parent_version=parent,
    )


def object_scores(
    name: str,
    n: int,
    keypoints: list[int],
    seed: int = 0,
    nan_fraction: float = 0.1,
    extras: bool = True,
) -> ObjectScores:
    """Random scores; ``extras``: with heatmap features and (for even seeds) group labels."""
    rng = np.random.default_rng(seed)
    scores = {}
    for i, function in enumerate(FUNCTIONS):
        matrix = rng.gamma(2.0, 1.0 + i, size=(n, len(keypoints)))
        matrix[rng.random(matrix.shape) < nan_fraction] = np.nan
        scores[function] = matrix
    refs = tuple(f"{name}/img{i:06d}/ann{i}" for i in range(n))
    features = {
        "peak_probability": rng.random((n, len(keypoints))),
        "gamma": rng.gamma(3.0, 1.0, size=(n, len(keypoints))),
    }
    groups = tuple(("", "camera-1", "camera-2")[i % 3] for i in range(n)) if seed % 2 == 0 else ()
    if not extras:
        return ObjectScores(name, np.asarray(keypoints), refs, scores)
    return ObjectScores(name, np.asarray(keypoints), refs, scores, features=features, groups=groups)


def score_table(n: int = 20, seed: int = 0, extras: bool = True) -> ScoreTable:
    """Two objects; ``extras``: with features and groups (False: as stored before migration 4)."""
    return ScoreTable(
        (
            object_scores("mug", n, [0, 1, 2, 3], seed=seed, extras=extras),
            object_scores("bottle", max(1, n // 2), [4, 5, 6, 7, 8, 9, 10], seed=seed + 1, extras=extras),
        )
    )


def large_table(n: int) -> ScoreTable:
    """n instances of one object with 8 keypoints: 3 * n * 64 bytes of scores."""
    return ScoreTable((object_scores("car", n, list(range(8)), seed=7),))


def assert_tables_identical(actual: ScoreTable, expected: ScoreTable) -> None:
    """Same objects, ids, refs and bit-identical matrices (NaN payloads included)."""
    assert [b.object_name for b in actual.objects] == [b.object_name for b in expected.objects]
    for got, want in zip(actual.objects, expected.objects, strict=True):
        assert got.keypoint_ids.tolist() == want.keypoint_ids.tolist()
        assert got.instance_refs == want.instance_refs
        assert got.functions == want.functions
        for function in want.functions:
            assert got.scores[function].shape == want.scores[function].shape
            assert got.scores[function].tobytes() == want.scores[function].tobytes()
        assert sorted(got.features) == sorted(want.features)
        for feature, matrix in want.features.items():
            assert got.features[feature].tobytes() == matrix.tobytes()
        assert got.groups == want.groups
