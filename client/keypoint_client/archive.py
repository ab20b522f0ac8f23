"""Calibration batches as the service takes them: a zip of annotations.json and the images it names."""

from __future__ import annotations

import json
import os
import tempfile
import zipfile
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

ANNOTATIONS = "annotations.json"


@contextmanager
def calibration_zip(source: str | os.PathLike[str]) -> Iterator[Path]:
    """``source`` itself when it is a zip file; for a COCO folder, a temporary zip of it,
    removed afterwards."""
    path = Path(source)
    if not path.is_dir():
        if not zipfile.is_zipfile(path):
            raise ValueError(f"{path} is neither a folder holding {ANNOTATIONS} nor a zip file")
        yield path
        return
    with tempfile.TemporaryDirectory(prefix="keypoint-batch-") as scratch:
        archive = Path(scratch) / f"{path.name or 'batch'}.zip"
        zip_coco_folder(path, archive)
        yield archive


def zip_coco_folder(folder: Path, archive: Path) -> None:
    """Write ``annotations.json`` and every image file it names (``images[].file_name``, relative
    to ``folder``) into ``archive``. Files it names that are missing are left for the service to
    report, with every other problem of the batch."""
    annotations = folder / ANNOTATIONS
    try:
        document = json.loads(annotations.read_bytes())
    except FileNotFoundError:
        raise ValueError(f"{folder} has no {ANNOTATIONS} (COCO keypoints)") from None
    except json.JSONDecodeError as error:
        raise ValueError(f"{annotations} is not JSON: {error}") from None
    images = document.get("images", []) if isinstance(document, dict) else []
    names: set[str] = set()
    for entry in images if isinstance(images, list) else []:
        name = entry.get("file_name") if isinstance(entry, dict) else None
        if isinstance(name, str) and name:
            names.add(name)
    root = folder.resolve()
    with zipfile.ZipFile(archive, "w") as output:
        output.write(annotations, ANNOTATIONS, compress_type=zipfile.ZIP_DEFLATED)
        for name in sorted(names):
            file = (folder / name).resolve()
            # Never a file outside the folder, whatever annotations.json says.
            if file.is_relative_to(root) and file.is_file():  # images are compressed: stored as they are
                output.write(file, name, compress_type=zipfile.ZIP_STORED)
