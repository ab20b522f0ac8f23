"""From an uploaded zip to a validated batch, synchronously, so that bad batches get a 4xx.

Only scoring runs in the background; everything that can be refused (the archive, the
COCO file, the image headers, the version to append to) is refused before the 202.
"""

from __future__ import annotations

import shutil
import uuid
from dataclasses import dataclass
from pathlib import Path

from service.calibration.archive import ArchiveLimits, extract_zip
from service.calibration.calibrate import NamedBatch
from service.calibration.coco import load_coco_batch
from service.detector.manifest import Manifest
from service.errors import InvalidInput
from service.processes import process_folder


def process_uploads_dir(uploads_dir: Path, pid: int | None = None) -> Path:
    """This process's folder of upload workspaces: ``<uploads>/<host>--<pid>``, removed when it
    stops (uploads of jobs cancelled at shutdown); a starting server removes dead processes'
    folders (``remove_dead_process_folders``): a version is written in one transaction at the
    end of a job, so an orphaned upload was never stored."""
    return process_folder(uploads_dir, pid)


@dataclass(frozen=True)
class UploadWorkspace:
    """A private directory under this process's uploads folder for one upload; removed when done."""

    root: Path

    @classmethod
    def create(cls, uploads_dir: Path) -> UploadWorkspace:
        root = process_uploads_dir(uploads_dir) / uuid.uuid4().hex
        root.mkdir(parents=True)
        return cls(root)

    @property
    def archive(self) -> Path:
        return self.root / "batch.zip"

    def remove(self) -> None:
        shutil.rmtree(self.root, ignore_errors=True)


def batch_name(requested: str | None, sha256: str) -> str:
    if requested is None:
        return f"upload-{sha256[:12]}"
    name = requested.strip()
    if not name or len(name) > 200 or any(ch in name for ch in "\r\n\t"):
        raise InvalidInput("name must be 1 to 200 printable characters on one line")
    return name


def validate_upload(
    workspace: UploadWorkspace, name: str, sha256: str, manifest: Manifest, limits: ArchiveLimits
) -> NamedBatch:
    """Unzip within limits and validate the COCO batch against the manifest."""
    folder = extract_zip(workspace.archive, workspace.root / "batch", limits)
    workspace.archive.unlink()
    return NamedBatch(name=name, sha256=sha256, batch=load_coco_batch(folder, manifest))
