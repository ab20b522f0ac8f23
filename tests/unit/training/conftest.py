"""Shared fixtures: a tiny rendered split (2 images, fixed seed), generated once per session."""

from __future__ import annotations

from pathlib import Path

import pytest

TINY_SEED = 7
TINY_IMAGES = 2


@pytest.fixture(scope="session")
def tiny_split(tmp_path_factory: pytest.TempPathFactory) -> Path:
    from training.generate import generate

    out = tmp_path_factory.mktemp("tiny") / "split"
    generate(out, TINY_IMAGES, TINY_SEED, "smoke", progress=False)
    return out
