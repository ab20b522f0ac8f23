"""The options an upload is kept with for a retry: what comes back is what was asked."""

from __future__ import annotations

import pytest

from service.calibration.intake import UploadOptions
from service.calibration.stratification import DIFFICULTY, GROUP
from service.errors import InvalidInput


@pytest.mark.parametrize("stratify", [None, frozenset(), frozenset({GROUP}), frozenset({DIFFICULTY, GROUP})])
def test_kept_options_come_back_as_asked(stratify: frozenset[str] | None) -> None:
    options = UploadOptions(name="b", append_to=3, activate=True, force=True, reason="r", stratify=stratify)
    assert UploadOptions.from_json(options.as_json()) == options


def test_options_kept_by_an_older_server_name_the_strata_as_one_string() -> None:
    kept = {**UploadOptions().as_json(), "stratify": "difficulty+group"}
    assert UploadOptions.from_json(kept).stratify == {DIFFICULTY, GROUP}


def test_force_needs_a_reason_and_activation() -> None:
    with pytest.raises(InvalidInput, match="force needs a reason"):
        UploadOptions(activate=True, force=True, reason=" ")
    with pytest.raises(InvalidInput, match="force only applies when activating"):
        UploadOptions(force=True, reason="why")
