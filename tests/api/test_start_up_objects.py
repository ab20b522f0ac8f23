"""Start-up's objects are out of the garbage collector's sight while the app runs: a full
collection walks only what requests made (beside a flood each had cost 100 to 170 ms)."""

from __future__ import annotations

import gc
from pathlib import Path

from tests.api.in_process import InProcess


def test_a_full_collection_skips_what_start_up_made(tmp_path: Path) -> None:
    with InProcess(tmp_path / "data") as service:
        assert service.client.get("/readyz").status_code == 200
        frozen, walked = gc.get_freeze_count(), len(gc.get_objects())  # get_objects: what a collection walks
    assert frozen > 50_000, frozen  # the model, the store, FastAPI's and pydantic's schemas
    assert walked < frozen / 4, (walked, frozen)
    assert gc.get_freeze_count() == 0  # given back when the app stops: the next one freezes its own
