"""Retention writes answers in the background: every answer queued reaches the store, in batches, and
a shutdown while the store is away says what was lost instead of waiting for it."""

from __future__ import annotations

import logging
from datetime import timedelta
from pathlib import Path

import pytest

from calibration_store import open_store
from service.feedback.retention import Retention, RetentionRules, ServedRequest

RULES = RetentionRules(share=0.0, max_age=timedelta(days=1), max_rows=1000)
SERVED = ServedRequest({"epsilon": 0.1}, [], [], (64, 64), 640, 480)


def test_every_queued_answer_reaches_the_store(tmp_path: Path) -> None:
    store = open_store(f"sqlite://{tmp_path}/c.db")
    retention = Retention(store, "f" * 64, RULES)
    ids = [retention.retain(1, SERVED, f"{i:064x}", "cam", "client") for i in range(50)]
    retention.flush()
    assert all(store.retained_prediction(i) is not None for i in ids)
    kept = store.retained_prediction(ids[0])
    assert kept.record["image"]["width"] == 640 and kept.stream == "cam"
    retention.close()
    store.close()


def test_a_shutdown_with_the_store_away_logs_what_is_lost(
    tmp_path: Path, caplog: pytest.LogCaptureFixture
) -> None:
    store = open_store(f"sqlite://{tmp_path}/c.db")
    retention = Retention(store, "f" * 64, RULES)
    store.close()  # the store is gone: writes fail
    retention.retain(1, SERVED, "0" * 64, None, "client")
    with caplog.at_level(logging.WARNING, logger="service.feedback.retention"):
        retention.close(timeout_s=0.5)
    assert "1 retained predictions were not stored before shutdown" in caplog.text


def test_the_share_is_drawn() -> None:
    sampled = Retention(None, "f" * 64, RetentionRules(0.3, timedelta(days=1), 10), seed=1)
    draws = [sampled.wanted(False) for _ in range(2000)]
    assert 0.25 < sum(draws) / len(draws) < 0.35 and sampled.wanted(True)
    sampled.close()


def test_frames_of_one_scene_share_a_look_named_by_its_first(tmp_path: Path) -> None:
    store = open_store(f"sqlite://{tmp_path}/c.db")
    retention = Retention(store, "f" * 64, RULES)

    def at(x: float) -> ServedRequest:
        instances = [{"object": "ape", "bbox": [x, 10.0, 50.0, 50.0], "group": None, "affine": None}]
        return ServedRequest({"epsilon": 0.1}, instances, [], (64, 64), 640, 480)

    frames = [(10.0, "cam-1"), (12.0, "cam-1"), (300.0, "cam-1"), (12.0, "cam-2"), (14.0, None)]
    ids = [retention.retain(1, at(x), "0" * 64, stream, "robot") for x, stream in frames]
    retention.flush()
    looks = [store.retained_prediction(i).record["look"] for i in ids]
    # the camera moved 2 px: one scene; then a cut; another stream, and the caller's frames, apart
    assert looks == [ids[0], ids[0], ids[2], ids[3], ids[4]]
    retention.close()
    store.close()
