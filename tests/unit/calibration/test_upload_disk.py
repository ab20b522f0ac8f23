"""Unzipping uploads within a disk budget (issue 13 item 3), with real zip bombs.

A zip bomb's honest headers are refused before anything is written: beyond the uncompressed
limit (413), beyond what kept uploads may take together (CKS_MAX_UPLOADS_DISK_BYTES, 507) or
beyond the free space to leave (507). The streamed extraction counts the bytes it really
produces and stops at its budget.
"""

from __future__ import annotations

import shutil
import zipfile
from pathlib import Path

import pytest

from benchmarks.faults_clients import zip_bomb
from service.calibration.archive import (
    MAX_UNCOMPRESSED_BYTES,
    ArchiveLimits,
    BudgetExceeded,
    DiskBudget,
    InsufficientStorage,
    copy_limited,
    extract_zip,
)
from service.errors import PayloadTooLarge, ServiceError

MiB = 2**20
BOMB = 64 * MiB


@pytest.fixture(scope="module")
def bomb(tmp_path_factory: pytest.TempPathFactory) -> Path:
    path = tmp_path_factory.mktemp("bomb") / "bomb.zip"
    path.write_bytes(zip_bomb(BOMB))
    assert path.stat().st_size < BOMB / 500
    return path


@pytest.fixture
def kept(tmp_path: Path) -> Path:
    """A folder of kept uploads already holding 10 MiB."""
    folder = tmp_path / "jobs"
    (folder / "some-job").mkdir(parents=True)
    (folder / "some-job" / "batch.zip").write_bytes(bytes(10 * MiB))
    return folder


def refused(bomb: Path, dest: Path, limits: ArchiveLimits, disk: DiskBudget | None = None) -> ServiceError:
    with pytest.raises(ServiceError) as error:
        extract_zip(bomb, dest, limits, disk)
    assert not dest.exists(), "a refused archive left files behind"
    return error.value


def test_the_issue_bomb_is_beyond_the_default_uncompressed_limit() -> None:
    """Issue 13: a 7.5 GiB zip bomb was within the default limit and wrote 7.7 GB to disk."""
    assert MAX_UNCOMPRESSED_BYTES < 7.5 * 2**30


def test_a_bomb_beyond_the_uncompressed_limit_writes_nothing(bomb: Path, tmp_path: Path) -> None:
    error = refused(bomb, tmp_path / "out", ArchiveLimits(10, BOMB - 1))
    assert isinstance(error, PayloadTooLarge) and "uncompressed size" in error.detail


def test_a_bomb_beyond_the_disk_budget_writes_nothing(bomb: Path, tmp_path: Path, kept: Path) -> None:
    budget = DiskBudget((kept,), max_bytes=BOMB + 5 * MiB, min_free_bytes=0)
    error = refused(bomb, tmp_path / "out", ArchiveLimits(10, 2 * BOMB), budget)
    assert isinstance(error, InsufficientStorage) and error.status == 507, error
    assert "CKS_MAX_UPLOADS_DISK_BYTES" in error.detail and str(10 * MiB) in error.detail, error.detail


def test_a_bomb_beyond_the_free_space_writes_nothing(bomb: Path, tmp_path: Path, kept: Path) -> None:
    free = shutil.disk_usage(tmp_path).free
    budget = DiskBudget((kept,), max_bytes=2**62, min_free_bytes=free - BOMB // 2)
    error = refused(bomb, tmp_path / "out", ArchiveLimits(10, 2 * BOMB), budget)
    assert isinstance(error, InsufficientStorage) and "bytes free" in error.detail, error


def test_a_bomb_within_every_limit_is_unzipped(bomb: Path, tmp_path: Path, kept: Path) -> None:
    budget = DiskBudget((kept,), max_bytes=BOMB + 11 * MiB, min_free_bytes=MiB)
    folder = extract_zip(bomb, tmp_path / "out", ArchiveLimits(10, BOMB + 100), budget)
    assert (folder / "images" / "bomb.png").stat().st_size == BOMB


def test_streaming_stops_at_the_budget(bomb: Path, tmp_path: Path) -> None:
    """The running count reads at most one byte past the budget and writes none past it."""
    with zipfile.ZipFile(bomb) as archive, archive.open("images/bomb.png") as src:
        with open(tmp_path / "out", "wb") as out, pytest.raises(BudgetExceeded):
            copy_limited(src, out, 3 * MiB)
        assert src.tell() == 3 * MiB + 1
    assert (tmp_path / "out").stat().st_size <= 3 * MiB
