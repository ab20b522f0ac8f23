"""A labeled COCO-keypoints batch (``annotations.json`` and its images, read by their headers),
validated against the manifest; every problem is reported in one ``InvalidInput``. Keypoints are
``x, y, v`` triples: ``v = 0`` not labeled (NaN), 1 (occluded) or 2 labeled. An annotation whose
box breaks the predict rule (``detector.boxes``) is rejected: listed with its reason, left out.
"""

from __future__ import annotations

import hashlib
import json
import math
import re
from collections.abc import Mapping
from dataclasses import dataclass, field
from pathlib import Path, PurePosixPath
from typing import Any

import numpy as np

from service.detector.boxes import box_problem
from service.detector.images import ImageHeader, read_image_header
from service.detector.manifest import Manifest, ObjectSpec
from service.errors import InvalidInput, PayloadTooLarge, UnsupportedMediaType, capped

ANNOTATIONS_FILENAME = "annotations.json"
MAX_REPORTED_PROBLEMS = 50
#: most bytes of annotations.json, checked before it is parsed (parsing holds the interpreter)
MAX_ANNOTATIONS_BYTES = 16 * 2**20
#: most annotations of a batch, checked before any is read
MAX_ANNOTATIONS = 20_000
HEADER_PREFIX_BYTES = 64 * 1024
_GROUP_RE = re.compile(r"^[\x20-\x7e]{1,64}$")  # the store's rule for group labels
_INVALID = object()


def check_annotations_size(size: int, where: str) -> None:
    """413 for an ``annotations.json`` of ``size`` bytes beyond MAX_ANNOTATIONS_BYTES."""
    if size > MAX_ANNOTATIONS_BYTES:
        raise PayloadTooLarge(
            f"{where} takes {size} bytes, above the limit of {MAX_ANNOTATIONS_BYTES} bytes:"
            " split the batch into smaller uploads"
        )


@dataclass(frozen=True)
class ImageRecord:
    id: int
    file_name: str
    path: Path
    width: int
    height: int


@dataclass(frozen=True, eq=False)
class LabeledInstance:
    """``bbox`` x, y, w, h; read-only ``keypoints`` (K, 2) pixels, NaN: not labeled; ``group``: a site."""

    image_id: int
    annotation_id: int
    object_name: str
    bbox: np.ndarray
    keypoints: np.ndarray
    group: str | None = None


@dataclass(frozen=True)
class Rejection:
    """An instance left out of a calibration (a rule it breaks, or a repeat), and why."""

    image_id: int
    annotation_id: int
    reason: str

    def describe(self) -> str:
        return f"image {self.image_id}, annotation {self.annotation_id}: {self.reason}"


@dataclass(frozen=True)
class CocoBatch:
    """A validated batch: images by id, instances in file order, the annotations rejected."""

    folder: Path
    sha256: str
    images: Mapping[int, ImageRecord]
    instances: tuple[LabeledInstance, ...]
    rejected: tuple[Rejection, ...] = ()

    @property
    def count(self) -> int:
        return len(self.instances)

    @property
    def annotations(self) -> int:
        return len(self.instances) + len(self.rejected)

    def instances_by_image(self) -> dict[int, list[LabeledInstance]]:
        groups: dict[int, list[LabeledInstance]] = {}
        for instance in self.instances:
            groups.setdefault(instance.image_id, []).append(instance)
        return groups


@dataclass(frozen=True)
class NamedBatch:
    """A validated COCO batch with the name and sha256 it is recorded under."""

    name: str
    sha256: str
    batch: CocoBatch


def load_coco_batch(folder: Path, manifest: Manifest, bounded: bool = False) -> CocoBatch:
    """The validated batch, or one ``InvalidInput`` listing every problem (``bounded``: 413s too)."""
    folder = Path(folder)
    path = folder / ANNOTATIONS_FILENAME
    if path.is_symlink() or not path.is_file():
        raise InvalidInput(f"{path.name} is missing from the batch folder (or is not a regular file)")
    if bounded:
        check_annotations_size(path.stat().st_size, ANNOTATIONS_FILENAME)
    raw = path.read_bytes()
    sections = _sections(raw)
    if bounded and len(sections["annotations"]) > MAX_ANNOTATIONS:
        raise PayloadTooLarge(
            f"{ANNOTATIONS_FILENAME} holds {len(sections['annotations'])} annotations, above the limit of"
            f" {MAX_ANNOTATIONS}: split the batch into smaller uploads"
        )
    problems = _Problems()
    categories = _read_categories(sections["categories"], manifest, problems)
    images, refused_images = _read_images(sections["images"], folder, problems)
    reader = _AnnotationReader(manifest, images, refused_images, categories, problems)
    entries = enumerate(sections["annotations"])
    instances = [i for n, entry in entries if (i := reader.read(f"annotations[{n}]", entry)) is not None]
    if not sections["annotations"]:
        problems.add("annotations", "is empty; a calibration batch needs at least one labeled instance")
    problems.raise_if_any()
    return CocoBatch(
        folder, hashlib.sha256(raw).hexdigest(), images, tuple(instances), tuple(reader.rejected)
    )


class _Problems(list[str]):
    def add(self, where: str, what: str) -> None:
        self.append(f"{where}: {what}")

    def raise_if_any(self) -> None:
        if self:
            raise InvalidInput(
                f"{ANNOTATIONS_FILENAME} has {len(self)} problem(s); first: {self[0]}",
                errors=capped(self, MAX_REPORTED_PROBLEMS),
            )


def _short(value: Any) -> str:
    """A bounded-size rendering of an untrusted value for a message."""
    if isinstance(value, list | dict):
        return f"{_type_name(value)} of {len(value)} items"
    text = repr(value[:41] if isinstance(value, str) else value)
    return text if len(text) <= 40 else text[:37] + "..."


def _type_name(value: Any) -> str:
    names = {dict: "an object", list: "a list", str: "a string", bool: "a boolean", type(None): "null"}
    return names.get(type(value), type(value).__name__)


def _is_int(value: Any) -> bool:
    return isinstance(value, int) and not isinstance(value, bool)


def _sections(raw: bytes) -> dict[str, list[Any]]:
    try:
        doc = json.loads(raw)
    except (ValueError, RecursionError) as exc:  # JSONDecodeError and UnicodeDecodeError are ValueErrors
        raise InvalidInput(f"{ANNOTATIONS_FILENAME} is not valid JSON: {exc}") from exc
    if not isinstance(doc, dict):
        raise InvalidInput(
            f"{ANNOTATIONS_FILENAME} must be a JSON object with keys images, categories and annotations; "
            f"got {_type_name(doc)}"
        )
    problems = _Problems()
    for key in ("images", "categories", "annotations"):
        if key not in doc:
            problems.add(key, "is missing (COCO keypoints needs images, categories and annotations)")
        elif not isinstance(doc[key], list):
            problems.add(key, f"must be a list, got {_type_name(doc[key])}")
    problems.raise_if_any()
    return {key: doc[key] for key in ("images", "categories", "annotations")}


def _read_categories(entries: list[Any], manifest: Manifest, problems: _Problems) -> dict[int, str]:
    """Category id -> name (names are checked against the manifest where annotations use them)."""
    names: dict[int, str] = {}
    for i, entry in enumerate(entries):
        where = f"categories[{i}]"
        if not isinstance(entry, dict):
            problems.add(where, f"must be an object, got {_type_name(entry)}")
            continue
        cat_id, name, keypoints = entry.get("id"), entry.get("name"), entry.get("keypoints")
        if not _is_int(cat_id):
            problems.add(where, f"id must be an integer, got {_short(cat_id)}")
        elif not isinstance(name, str):
            problems.add(where, f"name must be a string, got {_short(name)}")
        elif cat_id in names:
            problems.add(where, f"duplicate category id {cat_id}")
        else:
            names[cat_id] = name
            if keypoints is None or name not in manifest.object_names:
                continue
            if not isinstance(keypoints, list):
                problems.add(where, f"keypoints must be a list of names, got {_type_name(keypoints)}")
            elif len(keypoints) != (expected := len(manifest.object(name).keypoints)):
                problems.add(
                    where,
                    f"category {name!r} lists {len(keypoints)} keypoint names but model object {name!r} "
                    f"has {expected} keypoints",
                )
    return names


def _read_images(
    entries: list[Any], folder: Path, problems: _Problems
) -> tuple[dict[int, ImageRecord], set[int]]:
    """Valid images by id, and the ids of entries refused (their problems are recorded)."""
    root = folder.resolve()
    images: dict[int, ImageRecord] = {}
    refused: set[int] = set()
    for i, entry in enumerate(entries):
        record = _read_image(f"images[{i}]", entry, root, problems)
        if record is None:
            if isinstance(entry, dict) and _is_int(entry.get("id")):
                refused.add(entry["id"])
        elif record.id in images:
            problems.add(f"images[{i}]", f"duplicate image id {record.id}")
        else:
            images[record.id] = record
    return images, refused


def _read_image(where: str, entry: Any, root: Path, problems: _Problems) -> ImageRecord | None:
    if not isinstance(entry, dict):
        problems.add(where, f"must be an object, got {_type_name(entry)}")
        return None
    fields_ok = True
    for key in ("id", "width", "height"):
        value = entry.get(key)
        if not _is_int(value) or (key != "id" and value <= 0):
            kind = "an integer" if key == "id" else "a positive integer"
            problems.add(where, f"{key} must be {kind}, got {_short(value)}")
            fields_ok = False
    file_name = entry.get("file_name")
    if not isinstance(file_name, str) or not file_name:
        problems.add(where, f"file_name must be a non-empty string, got {_short(file_name)}")
        return None
    where = f"{where} ({file_name!r})"
    if problem := _file_name_problem(file_name, root):
        problems.add(where, problem)
    if problem or not fields_ok:
        return None
    path = (root / file_name).resolve()
    record = ImageRecord(entry["id"], file_name, path, entry["width"], entry["height"])
    try:
        header = _file_header(record.path)
    except UnsupportedMediaType:
        problems.add(where, "is not a JPEG or PNG image")
        return record
    except (InvalidInput, OSError) as exc:
        problems.add(where, f"cannot be read as an image ({exc})")
        return record
    declared, actual = f"{record.width}x{record.height}", f"{header.width}x{header.height}"
    if declared != actual:
        problems.add(
            where, f"declares {declared} but the file is {actual} (width x height); fix width/height"
        )
    return record


def _file_name_problem(file_name: str, root: Path) -> str | None:
    """Why ``file_name`` does not name a regular file inside ``root`` (no link on the way), or None."""
    if "\x00" in file_name:
        return "file_name contains a NUL character"
    if "\\" in file_name:
        return "file_name contains a backslash; use '/' as the path separator"
    if file_name.startswith("/") or (len(file_name) > 1 and file_name[1] == ":"):
        return "file_name is an absolute path; give it relative to annotations.json"
    if ".." in PurePosixPath(file_name).parts:
        return "file_name contains '..' and would escape the batch folder"
    path = root
    for part in PurePosixPath(file_name).parts:
        path = path / part
        if path.is_symlink():
            return f"{path.relative_to(root)} is a symbolic link; images must be regular files"
    path = (root / file_name).resolve()
    if not path.is_relative_to(root):
        return "resolves outside the batch folder"
    return None if path.is_file() else "the image file is missing from the batch"


def _file_header(path: Path) -> ImageHeader:
    """The header from the file's first bytes, or from the whole file if they do not suffice."""
    with open(path, "rb") as f:
        prefix = f.read(HEADER_PREFIX_BYTES)
        try:
            return read_image_header(prefix)
        except InvalidInput:
            if len(prefix) < HEADER_PREFIX_BYTES:
                raise
            return read_image_header(prefix + f.read())


@dataclass
class _AnnotationReader:
    manifest: Manifest
    images: dict[int, ImageRecord]
    refused_images: set[int]  # already reported: annotations on them are skipped silently
    categories: dict[int, str]
    problems: _Problems
    seen_ids: set[int] = field(default_factory=set)
    rejected: list[Rejection] = field(default_factory=list)

    def read(self, where: str, entry: Any) -> LabeledInstance | None:
        if not isinstance(entry, dict):
            self.problems.add(where, f"must be an object, got {_type_name(entry)}")
            return None
        ann_id = self._annotation_id(where, entry.get("id"))
        image = self._image(where, entry.get("image_id"))
        obj = self._object(where, entry.get("category_id"))
        bbox = self._numbers(f"{where}.bbox", entry.get("bbox"), 4)
        keypoints = self._keypoints(where, entry.get("keypoints"), obj)
        group = self._group(where, entry.get("group"))
        if any(v is None for v in (image, obj, bbox, keypoints, ann_id)) or group is _INVALID:
            return None
        bbox.flags.writeable = False
        if problem := box_problem(bbox, image.width, image.height):
            self.rejected.append(Rejection(image.id, ann_id, f"{where}.bbox: {problem}"))
            return None
        return LabeledInstance(image.id, ann_id, obj.name, bbox, keypoints, group)

    def _group(self, where: str, value: Any) -> Any:
        if value is None or (isinstance(value, str) and _GROUP_RE.match(value)):
            return value
        self.problems.add(where, f"group must be 1-64 printable ASCII characters, got {_short(value)}")
        return _INVALID

    def _annotation_id(self, where: str, value: Any) -> int | None:
        if not _is_int(value):
            self.problems.add(where, f"id must be an integer, got {_short(value)}")
            return None
        if value in self.seen_ids:
            self.problems.add(where, f"duplicate annotation id {value}")
            return None
        self.seen_ids.add(value)
        return value

    def _image(self, where: str, value: Any) -> ImageRecord | None:
        if not _is_int(value):
            self.problems.add(where, f"image_id must be an integer, got {_short(value)}")
            return None
        image = self.images.get(value)
        if image is None and value not in self.refused_images:
            self.problems.add(where, f"image_id {value} is not an id in images")
        return image

    def _object(self, where: str, value: Any) -> ObjectSpec | None:
        if not _is_int(value):
            self.problems.add(where, f"category_id must be an integer, got {_short(value)}")
            return None
        name = self.categories.get(value)
        if name is None:
            known = ", ".join(str(c) for c in sorted(self.categories)[:20]) or "none"
            self.problems.add(where, f"category_id {value} is not among the categories (ids: {known})")
            return None
        if name not in self.manifest.object_names:
            known = ", ".join(self.manifest.object_names)
            self.problems.add(
                where,
                f"category {name!r} is not an object of model {self.manifest.name!r} (known: {known})",
            )
            return None
        return self.manifest.object(name)

    def _numbers(self, where: str, value: Any, count: int) -> np.ndarray | None:
        """A list of exactly ``count`` finite numbers as float64, or None after recording why."""
        if not isinstance(value, list):
            self.problems.add(where, f"must be a list of {count} numbers, got {_type_name(value)}")
            return None
        if len(value) != count:
            self.problems.add(where, f"has {len(value)} numbers, expected {count}")
            return None
        numbers = [self._number(f"{where}[{j}]", v) for j, v in enumerate(value)]
        return None if None in numbers else np.asarray(numbers, dtype=np.float64)

    def _number(self, where: str, value: Any) -> float | None:
        if isinstance(value, bool) or not isinstance(value, int | float):
            if isinstance(value, str) and _nonfinite_text(value):
                self.problems.add(where, f"is not a finite number ({value!r})")
            else:
                self.problems.add(where, f"must be a number, got {_type_name(value)} {_short(value)}")
            return None
        try:
            number = float(value)
        except OverflowError:
            number = math.inf
        if not math.isfinite(number):
            self.problems.add(where, f"is not a finite number ({_short(value)})")
            return None
        return number

    def _keypoints(self, where: str, value: Any, obj: ObjectSpec | None) -> np.ndarray | None:
        if obj is None:
            return None
        k = len(obj.keypoints)
        where = f"{where}.keypoints"
        if isinstance(value, list) and len(value) != 3 * k:
            self.problems.add(
                where,
                f"has {len(value)} numbers but object {obj.name!r} has {k} keypoints "
                f"(expected 3 x {k} = {3 * k} values x, y, v)",
            )
            return None
        if (flat := self._numbers(where, value, 3 * k)) is None:
            return None
        triples = flat.reshape(k, 3)
        bad = [j for j, v in enumerate(triples[:, 2]) if v not in (0, 1, 2)]
        for j in bad:
            name = self.manifest.keypoints[obj.keypoints[j]].name
            self.problems.add(
                f"{where}[{3 * j + 2}]",
                f"visibility of keypoint {j} ({name!r}) is {triples[j, 2]:g}; use 0 (not labeled), "
                "1 (occluded) or 2 (visible)",
            )
        if bad:
            return None
        points = triples[:, :2].copy()
        points[triples[:, 2] == 0] = np.nan
        points.flags.writeable = False
        return points


def _nonfinite_text(text: str) -> bool:
    try:
        return not math.isfinite(float(text))
    except ValueError:
        return False
