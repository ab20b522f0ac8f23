"""A labeled calibration batch in COCO-keypoints form, validated against the model manifest.

The folder holds ``annotations.json`` (``images``, ``categories``, ``annotations``) and
the image files it names. Every problem found is collected (the first
``MAX_REPORTED_PROBLEMS`` are listed) and reported in one ``InvalidInput``, so an
operator can fix a batch in one pass. Image files are checked through their headers
only; pixels are decoded later by the scoring job.

Category names must equal manifest object names and an annotation's ``keypoints`` hold
``3 * K`` numbers ``x, y, v`` in the object's manifest keypoint order. ``v = 0`` means
not labeled (the row becomes NaN); ``v = 1`` (labeled, occluded) and ``v = 2`` count
as labeled. Labeled points may lie outside the image (occluded or out-of-crop).

A well-formed annotation whose box breaks the rule every predict box obeys
(``service.detector.boxes``) is not a problem of the file: it is *rejected*, listed in
``CocoBatch.rejected`` with the reason, and left out, as prediction would refuse it.
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
from service.errors import InvalidInput, PayloadTooLarge, UnsupportedMediaType

ANNOTATIONS_FILENAME = "annotations.json"
MAX_REPORTED_PROBLEMS = 50
ANNOTATIONS_BYTES_SETTING = "CKS_MAX_ANNOTATIONS_BYTES"
ANNOTATIONS_SETTING = "CKS_MAX_ANNOTATIONS"


@dataclass(frozen=True)
class AnnotationLimits:
    """Most bytes ``annotations.json`` may take (checked before it is parsed: parsing holds the
    interpreter, predictions of this process included) and most annotations it may hold
    (checked before any is read)."""

    max_bytes: int
    max_annotations: int

    def check_size(self, size: int, where: str) -> None:
        """413 for an ``annotations.json`` of ``size`` bytes beyond ``max_bytes``."""
        if size > self.max_bytes:
            raise PayloadTooLarge(
                f"{where} takes {size} bytes, above the limit of {self.max_bytes} bytes"
                f" ({ANNOTATIONS_BYTES_SETTING}): split the batch into smaller uploads"
            )


HEADER_PREFIX_BYTES = 64 * 1024
VISIBILITY_VALUES = (0, 1, 2)
_GROUP_RE = re.compile(r"^[\x20-\x7e]{1,64}$")  # the store's rule for group labels
_INVALID = object()


@dataclass(frozen=True)
class ImageRecord:
    """One image of the batch: its COCO id, name, resolved path and declared size."""

    id: int
    file_name: str
    path: Path
    width: int
    height: int


@dataclass(frozen=True, eq=False)
class LabeledInstance:
    """One labeled object: ``bbox`` ``(4,)`` as x, y, w and ``keypoints`` ``(K, 2)`` image pixels.

    Rows of ``keypoints`` that were not labeled (``v = 0``) are NaN. Arrays are read-only.
    ``group`` is the annotation's optional ``"group"`` attribute (a camera, a site: the
    caller's Mondrian group), None when absent.
    """

    image_id: int
    annotation_id: int
    object_name: str
    bbox: np.ndarray
    keypoints: np.ndarray
    group: str | None = None

    @property
    def labeled(self) -> np.ndarray:
        """``(K,)`` bool: which keypoints carry a label."""
        return ~np.isnan(self.keypoints[:, 0])

    @property
    def num_labeled(self) -> int:
        return int(self.labeled.sum())


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
    """A validated batch: images by id, instances in file order, sha256 of annotations.json,
    and the well-formed annotations rejected by the box rule."""

    folder: Path
    sha256: str
    images: Mapping[int, ImageRecord]
    instances: tuple[LabeledInstance, ...]
    rejected: tuple[Rejection, ...] = ()

    @property
    def count(self) -> int:
        """Number of labeled instances."""
        return len(self.instances)

    @property
    def annotations(self) -> int:
        """Number of annotations read: the instances plus the rejected ones."""
        return len(self.instances) + len(self.rejected)

    def instances_by_image(self) -> dict[int, list[LabeledInstance]]:
        """Instances grouped by image id, in file order (images without instances are absent)."""
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


def load_coco_batch(folder: Path, manifest: Manifest, limits: AnnotationLimits | None = None) -> CocoBatch:
    """Read and validate ``folder/annotations.json`` against ``manifest``.

    Raises one ``InvalidInput`` whose ``errors`` lists every problem found (capped at
    ``MAX_REPORTED_PROBLEMS``): malformed JSON or structure, unknown objects, wrong
    keypoint counts, non-finite numbers, bad visibilities, boxes outside their image,
    unknown or duplicate ids, unsafe, missing or mismatching image files, no annotations.
    ``PayloadTooLarge`` beyond ``limits`` (None: unbounded).
    """
    folder = Path(folder)
    raw = _read_annotations(folder, limits)
    sections = _sections(_parse_json(raw))
    if limits is not None and len(sections["annotations"]) > limits.max_annotations:
        raise PayloadTooLarge(
            f"{ANNOTATIONS_FILENAME} holds {len(sections['annotations'])} annotations, above the limit of"
            f" {limits.max_annotations} ({ANNOTATIONS_SETTING}): split the batch into smaller uploads"
        )
    problems = _Problems()
    categories = _read_categories(sections["categories"], manifest, problems)
    images, refused_images = _read_images(sections["images"], folder, problems)
    reader = _AnnotationReader(manifest, images, refused_images, categories, problems)
    instances = reader.read(sections["annotations"])
    if not sections["annotations"]:
        problems.add("annotations", "is empty; a calibration batch needs at least one labeled instance")
    problems.raise_if_any()
    digest = hashlib.sha256(raw).hexdigest()
    return CocoBatch(folder, digest, images, tuple(instances), tuple(reader.rejected))


# ---------------------------------------------------------------- problems


@dataclass
class _Problems:
    items: list[str] = field(default_factory=list)

    def add(self, where: str, what: str) -> None:
        self.items.append(f"{where}: {what}")

    def raise_if_any(self) -> None:
        if not self.items:
            return
        shown = self.items[:MAX_REPORTED_PROBLEMS]
        if len(self.items) > len(shown):
            shown.append(f"... and {len(self.items) - len(shown)} more")
        raise InvalidInput(
            f"{ANNOTATIONS_FILENAME} has {len(self.items)} problem(s); first: {self.items[0]}",
            errors=shown,
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


# ---------------------------------------------------------------- document


def _read_annotations(folder: Path, limits: AnnotationLimits | None) -> bytes:
    path = folder / ANNOTATIONS_FILENAME
    if path.is_symlink() or not path.is_file():
        raise InvalidInput(
            f"{ANNOTATIONS_FILENAME} is missing from the batch folder (or is not a regular file)"
        )
    if limits is not None:
        limits.check_size(path.stat().st_size, ANNOTATIONS_FILENAME)
    return path.read_bytes()


def _parse_json(raw: bytes) -> Any:
    try:
        return json.loads(raw)
    except (ValueError, RecursionError) as exc:  # JSONDecodeError and UnicodeDecodeError are ValueErrors
        raise InvalidInput(f"{ANNOTATIONS_FILENAME} is not valid JSON: {exc}") from exc


def _sections(doc: Any) -> dict[str, list[Any]]:
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


# ---------------------------------------------------------------- categories


def _read_categories(entries: list[Any], manifest: Manifest, problems: _Problems) -> dict[int, str]:
    """Category id -> name. Names are checked against the manifest where annotations use them."""
    names: dict[int, str] = {}
    for i, entry in enumerate(entries):
        where = f"categories[{i}]"
        if not isinstance(entry, dict):
            problems.add(where, f"must be an object, got {_type_name(entry)}")
            continue
        cat_id, name = entry.get("id"), entry.get("name")
        if not _is_int(cat_id):
            problems.add(where, f"id must be an integer, got {_short(cat_id)}")
        elif not isinstance(name, str):
            problems.add(where, f"name must be a string, got {_short(name)}")
        elif cat_id in names:
            problems.add(where, f"duplicate category id {cat_id}")
        else:
            names[cat_id] = name
            _check_category_keypoints(where, entry.get("keypoints"), name, manifest, problems)
    return names


def _check_category_keypoints(
    where: str, keypoints: Any, name: str, manifest: Manifest, problems: _Problems
) -> None:
    if keypoints is None or name not in manifest.object_names:
        return
    if not isinstance(keypoints, list):
        problems.add(where, f"keypoints must be a list of names, got {_type_name(keypoints)}")
        return
    expected = len(manifest.object(name).keypoints)
    if len(keypoints) != expected:
        problems.add(
            where,
            f"category {name!r} lists {len(keypoints)} keypoint names but model object {name!r} "
            f"has {expected} keypoints",
        )


# ---------------------------------------------------------------- images


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
            continue
        if record.id in images:
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
    path = _image_path(where, file_name, root, problems)
    if path is None or not fields_ok:
        return None
    record = ImageRecord(entry["id"], file_name, path, entry["width"], entry["height"])
    _check_image_file(where, record, problems)
    return record


def _image_path(where: str, file_name: str, root: Path, problems: _Problems) -> Path | None:
    """The file's resolved path inside ``root``, or None after recording why not."""
    problem = _file_name_problem(file_name) or _link_problem(file_name, root)
    if problem is None:
        path = (root / file_name).resolve()
        if not path.is_relative_to(root):
            problem = "resolves outside the batch folder"
        elif not path.is_file():
            problem = "the image file is missing from the batch"
        else:
            return path
    problems.add(where, problem)
    return None


def _link_problem(file_name: str, root: Path) -> str | None:
    """Refuse a symbolic link anywhere along the path below ``root``."""
    path = root
    for part in PurePosixPath(file_name).parts:
        path = path / part
        if path.is_symlink():
            return f"{path.relative_to(root)} is a symbolic link; images must be regular files"
    return None


def _file_name_problem(file_name: str) -> str | None:
    if "\x00" in file_name:
        return "file_name contains a NUL character"
    if "\\" in file_name:
        return "file_name contains a backslash; use '/' as the path separator"
    if file_name.startswith("/") or (len(file_name) > 1 and file_name[1] == ":"):
        return "file_name is an absolute path; give it relative to annotations.json"
    if ".." in PurePosixPath(file_name).parts:
        return "file_name contains '..' and would escape the batch folder"
    return None


def _check_image_file(where: str, record: ImageRecord, problems: _Problems) -> None:
    try:
        header = _file_header(record.path)
    except UnsupportedMediaType:
        problems.add(where, "is not a JPEG or PNG image")
        return
    except (InvalidInput, OSError) as exc:
        problems.add(where, f"cannot be read as an image ({exc})")
        return
    if (header.width, header.height) != (record.width, record.height):
        problems.add(
            where,
            f"declares {record.width}x{record.height} but the file is {header.width}x{header.height} "
            "(width x height); fix width/height",
        )


def _file_header(path: Path) -> ImageHeader:
    """Read the header from the file's first bytes, or from the whole file if they do not suffice."""
    with open(path, "rb") as f:
        prefix = f.read(HEADER_PREFIX_BYTES)
        try:
            return read_image_header(prefix)
        except InvalidInput:
            if len(prefix) < HEADER_PREFIX_BYTES:
                raise
            return read_image_header(prefix + f.read())


# ---------------------------------------------------------------- annotations


@dataclass
class _AnnotationReader:
    manifest: Manifest
    images: dict[int, ImageRecord]
    refused_images: set[int]  # already reported: annotations on them are skipped silently
    categories: dict[int, str]
    problems: _Problems
    seen_ids: set[int] = field(default_factory=set)
    rejected: list[Rejection] = field(default_factory=list)

    def read(self, entries: list[Any]) -> list[LabeledInstance]:
        instances = []
        for i, entry in enumerate(entries):
            instance = self._read_one(f"annotations[{i}]", entry)
            if instance is not None:
                instances.append(instance)
        return instances

    def _read_one(self, where: str, entry: Any) -> LabeledInstance | None:
        if not isinstance(entry, dict):
            self.problems.add(where, f"must be an object, got {_type_name(entry)}")
            return None
        ann_id = self._annotation_id(where, entry.get("id"))
        image = self._image(where, entry.get("image_id"))
        obj = self._object(where, entry.get("category_id"))
        bbox = self._bbox(where, entry.get("bbox"))
        keypoints = self._keypoints(where, entry.get("keypoints"), obj)
        group = self._group(where, entry.get("group"))
        if ann_id is None or image is None or obj is None or bbox is None or keypoints is None:
            return None
        if group is _INVALID:
            return None
        problem = box_problem(bbox, image.width, image.height)
        if problem:
            self.rejected.append(Rejection(image.id, ann_id, f"{where}.bbox: {problem}"))
            return None
        return LabeledInstance(image.id, ann_id, obj.name, bbox, keypoints, group)

    def _group(self, where: str, value: Any) -> Any:
        if value is None:
            return None
        if not isinstance(value, str) or not _GROUP_RE.match(value):
            self.problems.add(where, f"group must be 1-64 printable ASCII characters, got {_short(value)}")
            return _INVALID
        return value

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
        if any(n is None for n in numbers):
            return None
        return np.asarray(numbers, dtype=np.float64)

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

    def _bbox(self, where: str, value: Any) -> np.ndarray | None:
        bbox = self._numbers(f"{where}.bbox", value, 4)
        if bbox is not None:
            bbox.flags.writeable = False
        return bbox

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
        flat = self._numbers(where, value, 3 * k)
        if flat is None:
            return None
        triples = flat.reshape(k, 3)
        bad = [j for j, v in enumerate(triples[:, 2]) if v not in VISIBILITY_VALUES]
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
