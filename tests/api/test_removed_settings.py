"""A setting that is no longer read, still set by an operator, gets one warning at start-up."""

from __future__ import annotations

import logging
from pathlib import Path

import pytest
from fastapi.testclient import TestClient

from service.infra.settings import Settings
from service.serving.app import create_app


def test_a_removed_setting_still_set_is_named_with_what_replaced_it(
    tmp_path: Path, monkeypatch: pytest.MonkeyPatch, caplog: pytest.LogCaptureFixture
) -> None:
    monkeypatch.setenv("CKS_MAX_INFERENCE_BATCH", "32")
    monkeypatch.delenv("CKS_SOLO_INFERENCE_THREADS", raising=False)
    with (
        caplog.at_level(logging.WARNING),
        TestClient(create_app(Settings(data_dir=tmp_path, inference_threads=1))),
    ):
        pass
    removed = [record.getMessage() for record in caplog.records if "no longer read" in record.getMessage()]
    assert removed == [
        "CKS_MAX_INFERENCE_BATCH is no longer read: micro-batching was removed (it lost on CPU and GPU, see"
        " CHANGELOG); each request's crops are one run on its own thread, with CKS_INFERENCE_THREADS"
        " intra-op threads"
    ]
    assert all(
        record.levelno == logging.WARNING for record in caplog.records if record.getMessage() in removed
    )
