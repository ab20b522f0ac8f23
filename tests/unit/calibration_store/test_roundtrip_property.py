"""Property: any finite-or-NaN float64 matrix round-trips bit-exact through SQLite."""

from __future__ import annotations

from collections.abc import Iterator
from pathlib import Path

import numpy as np
import pytest
from hypothesis import given, settings
from hypothesis import strategies as st
from hypothesis.extra import numpy as hnp

from calibration_store import CalibrationStore, ObjectScores, ScoreTable, open_store
from tests.unit.calibration_store.factories import MODEL_A, assert_tables_identical, new_version

finite_or_nan = st.floats(allow_infinity=False, allow_nan=True, allow_subnormal=True, width=64)


@pytest.fixture(scope="module")
def sqlite_store(tmp_path_factory: pytest.TempPathFactory) -> Iterator[CalibrationStore]:
    path: Path = tmp_path_factory.mktemp("roundtrip") / "c.db"
    with open_store(f"sqlite://{path}") as store:
        yield store


@settings(max_examples=40, deadline=None)
@given(
    matrix=hnp.arrays(
        np.float64, hnp.array_shapes(min_dims=2, max_dims=2, max_side=12), elements=finite_or_nan
    ),
    refs_text=st.text(max_size=8),
)
def test_matrix_round_trip(sqlite_store: CalibrationStore, matrix: np.ndarray, refs_text: str) -> None:
    n, k = matrix.shape
    block = ObjectScores(
        "obj", np.arange(k) * 3, tuple(refs_text for _ in range(n)), {"peak": matrix, "cov": -matrix}
    )
    table = ScoreTable((block,))
    info = sqlite_store.create_version(new_version(), table)
    assert_tables_identical(sqlite_store.load_scores(MODEL_A, info.number), table)
