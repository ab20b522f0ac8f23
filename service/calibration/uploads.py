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


@dataclass(frozen=True)
class UploadWorkspace:
    """A private directory under the data directory for one upload; removed when done."""

    root: Path

    @classmethod
    def create(cls, uploads_dir: Path) -> UploadWorkspace:
        root = uploads_dir / uuid.uuid4().hex
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
