"""Content hashes of calibration instances (of the image file; of image hash, object, box and
labels), and the repeats they reveal: an instance counted twice voids n and the guarantee.
"""

from __future__ import annotations

import hashlib
import json
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass
from typing import Any

import numpy as np

from calibration_store import ScoreTable, SourceBatch
from service.calibration.coco import CocoBatch, Rejection

#: stands for the hash of an instance stored before hashes were kept (never a repeat)
UNKNOWN_DIGEST = "0" * 64


@dataclass(frozen=True)
class Fingerprint:
    image: str
    instance: str


def fingerprints(batch: CocoBatch) -> tuple[Fingerprint, ...]:
    """One fingerprint per instance of ``batch``, in order (each image file is read once)."""
    images = {instance.image_id for instance in batch.instances}
    digests = {i: hashlib.sha256(batch.images[i].path.read_bytes()).hexdigest() for i in images}
    pairs = [(digests[i.image_id], i) for i in batch.instances]
    return tuple(Fingerprint(d, instance_digest(d, i.object_name, i.bbox, i.keypoints)) for d, i in pairs)


def instance_digest(image_digest: str, object_name: str, bbox: Sequence[float], keypoints: np.ndarray) -> str:
    """The content hash of one instance: its image's, object, box and labels ((K, 2), NaN: none)."""
    labels = [[None if np.isnan(v) else float(v) for v in row] for row in keypoints]
    document = [image_digest, object_name, [float(v) for v in bbox], labels]
    canonical = json.dumps(document, separators=(",", ":"))
    return hashlib.sha256(canonical.encode()).hexdigest()


def find_repeats(
    batch: CocoBatch,
    prints: Sequence[Fingerprint],
    batch_sha256: str,
    parent: ScoreTable | None = None,
    parent_sources: Iterable[SourceBatch] = (),
    parent_number: int | None = None,
) -> list[Rejection]:
    """Instances of ``batch`` already counted, in the batch or in the version it extends."""
    where = f"version {parent_number}"
    for source in parent_sources:
        if source.sha256 == batch_sha256:
            reason = f"the same batch (sha256 {batch_sha256[:12]}) is already in {where} as {source.name!r}"
            return [Rejection(i.image_id, i.annotation_id, reason) for i in batch.instances]
    old_images, old_instances = stored_digests(parent)
    image_ids: dict[str, int] = {}
    seen: set[str] = set()
    repeats = []
    for instance, fingerprint in zip(batch.instances, prints, strict=True):
        first_id = image_ids.setdefault(fingerprint.image, instance.image_id)
        reason = None
        if fingerprint.image in old_images:
            reason = f"its image file is already in {where}"
        elif fingerprint.instance in old_instances:
            reason = f"the same instance is already in {where}"
        elif first_id != instance.image_id:
            reason = f"its image file repeats image {first_id} of this batch"
        elif fingerprint.instance in seen:
            reason = "the same instance (image, object, box, labels) appears earlier in this batch"
        seen.add(fingerprint.instance)
        if reason:
            repeats.append(Rejection(instance.image_id, instance.annotation_id, reason))
    return repeats


def instance_digests(table: ScoreTable) -> set[str]:
    """The content hashes of a version's instances (less those stored before hashes were kept)."""
    return stored_digests(table)[1]


def content_key(table: ScoreTable, strata: Iterable[str], scoring: Mapping[str, Any]) -> str | None:
    """One sha256 of what makes versions equal (None when an instance's hash is unknown)."""
    instances = instance_digests(table)
    if len(instances) != table.n_instances:
        return None
    document = {"instances": sorted(instances), "strata": sorted(strata), "scoring": dict(scoring)}
    return hashlib.sha256(json.dumps(document, sort_keys=True).encode()).hexdigest()


def stored_digests(table: ScoreTable | None) -> tuple[set[str], set[str]]:
    """The image and instance hashes a version holds (less those stored before hashes were kept)."""
    blocks = () if table is None else table.objects
    images = {digest for block in blocks for digest in block.image_hashes}
    instances = {digest for block in blocks for digest in block.instance_hashes}
    return images - {UNKNOWN_DIGEST}, instances - {UNKNOWN_DIGEST}
