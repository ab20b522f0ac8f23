"""The bundled model's labeled samples, and COCO-keypoints batch zips built from them for upload tests."""

from __future__ import annotations

import base64
import copy
import io
import json
import zipfile
from collections.abc import Callable
from dataclasses import dataclass
from pathlib import Path

from service.infra.settings import Settings


def model_dir() -> Path:
    """The served model: CKS_MODEL_DIR, or the bundled one (never written to)."""
    return Path(Settings().model.directory).resolve()


@dataclass(frozen=True)
class Sample:
    """One labeled instance of the bundled samples."""

    image_path: Path
    width: int
    height: int
    object: str
    bbox: list[float]
    keypoints: list[tuple[float, float, int]]  # x, y, v (v = 0: not labeled)


def load_samples(samples_dir: Path, doc: dict) -> list[Sample]:
    images = {image["id"]: image for image in doc["images"]}
    categories = {c["id"]: c["name"] for c in doc["categories"]}
    samples = []
    for ann in doc["annotations"]:
        image = images[ann["image_id"]]
        flat = ann["keypoints"]
        triples = [(flat[i], flat[i + 1], int(flat[i + 2])) for i in range(0, len(flat), 3)]
        samples.append(
            Sample(
                samples_dir / image["file_name"],
                image["width"],
                image["height"],
                categories[ann["category_id"]],
                list(ann["bbox"]),
                triples,
            )
        )
    return samples


def samples_by_image(samples: list[Sample]) -> dict[Path, list[Sample]]:
    grouped: dict[Path, list[Sample]] = {}
    for sample in samples:
        grouped.setdefault(sample.image_path, []).append(sample)
    return grouped


def b64(data: bytes) -> str:
    return base64.b64encode(data).decode("ascii")


Mutation = Callable[[dict, dict[str, bytes]], None]


def batch_files(samples_dir: Path, doc: dict, images: int | None = None) -> tuple[dict, dict[str, bytes]]:
    """annotations.json (as a dict) and the image files of the first ``images`` images."""
    doc = copy.deepcopy(doc)
    if images is not None:
        doc["images"] = doc["images"][:images]
        kept = {image["id"] for image in doc["images"]}
        doc["annotations"] = [a for a in doc["annotations"] if a["image_id"] in kept]
    files = {image["file_name"]: (samples_dir / image["file_name"]).read_bytes() for image in doc["images"]}
    return doc, files


def build_zip(
    doc: dict | bytes,
    files: dict[str, bytes],
    *,
    compression: int = zipfile.ZIP_DEFLATED,
    links: dict[str, str] | None = None,
) -> bytes:
    """A zip with annotations.json (a dict, or raw bytes as given), ``files`` and symlink entries."""
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w", compression=compression) as archive:
        raw = doc if isinstance(doc, bytes) else json.dumps(doc).encode()
        archive.writestr("annotations.json", raw)
        for name, data in files.items():
            archive.writestr(name, data)
        for name, target in (links or {}).items():
            info = zipfile.ZipInfo(name)
            info.create_system = 3  # unix, so external_attr carries the file type
            info.external_attr = (0o120777 << 16) & 0xFFFF0000  # S_IFLNK | 0777
            archive.writestr(info, target)
    return buffer.getvalue()


def batch_zip(
    samples_dir: Path, doc: dict, images: int | None = None, mutate: Mutation | None = None
) -> bytes:
    """A zip of the samples' COCO batch (the first ``images`` images), optionally mutated in place."""
    doc, files = batch_files(samples_dir, doc, images)
    if mutate is not None:
        mutate(doc, files)
    return build_zip(doc, files)


def count_instances(doc: dict, images: int | None = None) -> int:
    kept = {image["id"] for image in (doc["images"] if images is None else doc["images"][:images])}
    return sum(1 for a in doc["annotations"] if a["image_id"] in kept)
