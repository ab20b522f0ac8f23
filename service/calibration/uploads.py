"""Where received uploads live on disk: in this process's workspace folder while received (removed
if the process dies), then in ``<data>/jobs/<job id>`` until the job succeeds or fails; a job
interrupted by a crash, or failed for a full disk, keeps it and can be retried.
"""

from __future__ import annotations

import json
import logging
import shutil
import time
import uuid
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from calibration_store import CalibrationStore, StoreError
from service.infra.job_engine import retryable
from service.infra.processes import process_folder

log = logging.getLogger(__name__)


@dataclass(frozen=True)
class _UploadFolder:
    root: Path

    @property
    def archive(self) -> Path:
        return self.root / "batch.zip"

    def remove(self) -> None:
        shutil.rmtree(self.root, ignore_errors=True)


@dataclass(frozen=True)
class UploadWorkspace(_UploadFolder):
    """A private directory under this process's uploads folder for one upload; removed when done."""

    @classmethod
    def create(cls, uploads_dir: Path) -> UploadWorkspace:
        root = process_folder(uploads_dir) / uuid.uuid4().hex  # removed when the process stops
        root.mkdir(parents=True)
        return cls(root)


@dataclass(frozen=True)
class JobFolder(_UploadFolder):
    """The upload of one calibration job and its request, kept until the job succeeds or fails."""

    REQUEST = "request.json"
    UNCLAIMED_AFTER_S = 3600.0  # a folder without a job row this old was left by a crash

    @classmethod
    def of(cls, jobs_dir: Path, job_id: str) -> JobFolder:
        return cls(jobs_dir / job_id)

    @property
    def job_id(self) -> str:
        return self.root.name

    def adopt(self, workspace: UploadWorkspace) -> None:
        """Move a received upload here (same file system: one rename)."""
        self.root.parent.mkdir(parents=True, exist_ok=True)
        workspace.root.rename(self.root)

    def exists(self) -> bool:
        return (self.root / self.REQUEST).is_file()

    def save(self, request: dict[str, Any]) -> None:
        (self.root / self.REQUEST).write_text(json.dumps(request, sort_keys=True), encoding="utf-8")

    def load(self) -> dict[str, Any]:
        return json.loads((self.root / self.REQUEST).read_text(encoding="utf-8"))

    def move_to(self, other: JobFolder) -> None:
        self.root.rename(other.root)


def remove_spent_job_folders(jobs_dir: Path, store: CalibrationStore) -> None:
    """Remove kept uploads nobody can retry (of finished or pruned jobs, or left by a crash)."""
    if not jobs_dir.is_dir():
        return
    for root in jobs_dir.iterdir():
        try:
            job = store.get_job(root.name)
        except StoreError as error:
            log.warning("could not check kept uploads in %s: %s", jobs_dir, error)
            return
        unclaimed = job is None and time.time() - root.stat().st_mtime > JobFolder.UNCLAIMED_AFTER_S
        if unclaimed or (job is not None and job.finished and not retryable(job)):
            shutil.rmtree(root, ignore_errors=True)
