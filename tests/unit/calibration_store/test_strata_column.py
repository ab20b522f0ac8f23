"""A version's Mondrian strata (JSON) are stored with it and read back as written; versions
without strata read back None."""

from __future__ import annotations

from dataclasses import replace

import pytest

from calibration_store import CalibrationStore
from tests.unit.calibration_store.factories import MODEL_A, new_version, score_table

STRATA = {
    "spec": {
        "difficulty": {"signals": ["gamma", "peak_probability"], "bins": 3, "min_instances": 30},
        "group": True,
    },
    "groups": ["cam-1", "cam-2"],
    "bins": {
        "0": {
            "*": {
                "signals": ["gamma", "peak_probability"],
                "edges": [1.5],
                "counts": [40, 41],
                "inner_edges": [[], []],
            }
        }
    },
}


def test_strata_round_trip(store: CalibrationStore) -> None:
    with_strata = store.create_version(replace(new_version(), strata=STRATA), score_table(n=3))
    without = store.create_version(new_version(), score_table(n=3))
    assert with_strata.strata == STRATA == store.get_version(MODEL_A, with_strata.number).strata
    assert without.strata is None and store.list_versions(MODEL_A)[1].strata is None


def test_strata_must_be_a_json_object() -> None:
    with pytest.raises((TypeError, ValueError)):
        replace(new_version(), strata=["not", "an", "object"])
