"""create_first_version: the atomic bootstrap of a model's version 1, on both backends."""

from __future__ import annotations

import pytest

from calibration_store import open_store
from tests.unit.calibration_store.factories import MODEL_A, new_version, score_table


def test_a_model_with_a_version_is_not_bootstrapped_and_nothing_is_written(store_url: str) -> None:
    with open_store(store_url) as store:
        store.create_version(new_version(), score_table(n=4))
        counter = store.change_counter()
        assert store.create_first_version(new_version(note="late"), score_table(n=4), who="boot") is None
        assert [v.number for v in store.list_versions(MODEL_A)] == [1]
        assert store.active_version(MODEL_A) is None and store.change_counter() == counter
        info = store.create_version(new_version(), score_table(n=4))
        assert info.number == 2, "the refused bootstrap must not consume a number"


def test_the_activation_text_is_checked(store_url: str) -> None:
    with open_store(store_url) as store:
        with pytest.raises(ValueError, match="who"):
            store.create_first_version(new_version(), score_table(n=4), who=" ")
        with pytest.raises(ValueError, match="parent_version"):
            store.create_first_version(new_version(parent=1), score_table(n=4), who="boot")
        assert store.list_versions(MODEL_A) == []
