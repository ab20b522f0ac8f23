"""From a received upload to a validated batch, or a 4xx: everything that can refuse a batch runs
here, before an upload's 202, so a batch that would be refused never becomes a job.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import asdict, dataclass, replace
from itertools import compress
from pathlib import Path
from typing import Any

from calibration_store import CalibrationStore, ScoreTable, VersionInfo, VersionNotFound
from service.calibration.archive import DiskBudget, extract_zip
from service.calibration.coco import CocoBatch, NamedBatch, Rejection, load_coco_batch
from service.calibration.compatibility import version_incompatibility
from service.calibration.fingerprints import Fingerprint, find_repeats, fingerprints, instance_digests
from service.calibration.stratification import DIFFICULTY, GROUP, describe_kinds, parse_stratify, stored_kinds
from service.detector.session import Detector
from service.errors import Conflict, InvalidInput, NotFound, capped, disk_full_refused

#: how many repeats or rejections a refusal lists (the count is always given)
LISTED = 20
#: share of a batch's instances the box rule may reject, unless the upload says otherwise
MAX_REJECTED_SHARE = 0.0
#: a version's scores by number
Scores = Callable[[int], ScoreTable]


@dataclass(frozen=True)
class UploadOptions:
    """What the operator asked for with an upload (kept with it, for a retry)."""

    name: str | None = None
    note: str = ""
    append_to: int | None = None
    activate: bool = False
    force: bool = False
    reason: str = ""
    dedupe: bool = False
    allow_duplicate: bool = False
    max_rejected_share: float | None = None  # None: MAX_REJECTED_SHARE
    stratify: frozenset[str] | None = None  # None: difficulty strata when the scores carry heatmap features

    def __post_init__(self) -> None:
        if self.force and not self.reason.strip():
            raise InvalidInput(
                "force needs a reason (force=true&reason=..., or --force --reason ...):"
                " say why the guardrails may be overridden"
            )
        if self.force and not self.activate:
            raise InvalidInput("force only applies when activating (activate=true, or --activate)")
        if self.allow_duplicate and not self.reason.strip():
            raise InvalidInput(
                "allow_duplicate needs a reason (allow_duplicate=true&reason=...):"
                " say why a version equal to a stored one is wanted"
            )

    @property
    def rejected_share(self) -> float:
        return MAX_REJECTED_SHARE if self.max_rejected_share is None else self.max_rejected_share

    def as_json(self) -> dict[str, Any]:
        return {**asdict(self), "stratify": None if self.stratify is None else sorted(self.stratify)}

    @classmethod
    def from_json(cls, kept: dict[str, Any]) -> UploadOptions:
        stratify = kept.get("stratify")  # a list; "difficulty+group" in uploads kept by older servers
        return cls(**{**kept, "stratify": None if stratify is None else parse_stratify(stratify)})


@dataclass(frozen=True)
class Parent:
    info: VersionInfo
    scores: ScoreTable


@dataclass(frozen=True)
class ValidatedBatch:
    """A batch to score (repeats dropped), and the stored version it repeats (``allow_duplicate``)."""

    named: NamedBatch
    fingerprints: tuple[Fingerprint, ...]
    repeats_dropped: int
    rejected: tuple[Rejection, ...]
    parent: Parent | None = None
    duplicate_of: int | None = None

    @property
    def annotations(self) -> int:
        """Annotations the batch held before anything was left out."""
        return self.named.batch.annotations + self.repeats_dropped

    def moved(self, old: Path, new: Path) -> ValidatedBatch:
        """The same batch once the folder it was unzipped in was renamed from ``old`` to ``new``."""
        batch = self.named.batch
        was, now = old.resolve(), new.resolve()
        images = {i: replace(r, path=now / r.path.relative_to(was)) for i, r in batch.images.items()}
        moved = replace(batch, folder=new / batch.folder.relative_to(old), images=images)
        return replace(self, named=replace(self.named, batch=moved))


@dataclass(frozen=True)
class IntakeRules:
    disk: DiskBudget | None = None
    max_rejected_share: float = MAX_REJECTED_SHARE


class Intake:
    """Checks received uploads for one detector: its manifest, the versions of its store."""

    def __init__(
        self, store: CalibrationStore, detector: Detector, scores: Scores, rules: IntakeRules
    ) -> None:
        self._store, self._detector, self._scores, self._rules = store, detector, scores, rules

    def unpack(self, archive: Path, sha256: str, name: str | None) -> NamedBatch:
        """Unzip beside the zip (then removed) within the limits and the disk budget, and read it."""
        batch_name(name, sha256)  # refused before anything is unzipped
        with disk_full_refused("the unzipped upload"):  # what was unzipped is removed
            unzipped = extract_zip(archive, archive.parent / "batch", disk=self._rules.disk)
        archive.unlink()
        return self.read(unzipped, sha256, name)

    def read(self, folder: Path, sha256: str, name: str | None) -> NamedBatch:
        """The COCO batch of an unzipped ``folder`` (a kept upload), validated against the manifest."""
        batch = load_coco_batch(folder, self._detector.manifest, bounded=True)
        return NamedBatch(batch_name(name, sha256), sha256, batch)

    def validate(self, named: NamedBatch, options: UploadOptions) -> ValidatedBatch:
        """The parent read once (its scores go with the batch to its job), then the refusing rules."""
        parent = None
        if options.append_to is not None:
            parent = read_parent(self._store, self._detector, options.append_to, self._scores)
        if options.stratify is not None and GROUP in options.stratify:
            check_group_labels(named, parent)
        batch = check_batch(named, parent, dedupe=options.dedupe, max_rejected_share=options.rejected_share)
        return replace(batch, duplicate_of=self.duplicate_of(batch, options))

    def duplicate_of(self, batch: ValidatedBatch, options: UploadOptions) -> int | None:
        """The stored version the batch would repeat (409 unless ``allow_duplicate``), or None."""
        instances = {p.instance for p in batch.fingerprints}
        count = len(batch.fingerprints)
        if batch.parent is not None:
            instances |= instance_digests(batch.parent.scores)
            count += batch.parent.scores.n_instances
        return equal_version(self._store, self._detector, self._scores, instances, count, options)


def equal_version(
    store: CalibrationStore,
    detector: Detector,
    scores: Scores,
    instances: set[str],
    count: int,
    options: UploadOptions,
) -> int | None:
    """The stored version with the same instances and strata (409 unless ``allow_duplicate``)."""
    if len(instances) != count:  # instances stored before hashes were kept: nothing to compare
        return None
    for info in store.list_versions(detector.model_hash):
        stored = stored_kinds(info.strata)
        same_strata = stored <= {DIFFICULTY} if options.stratify is None else stored == options.stratify
        if info.n_instances != count or not same_strata or version_incompatibility(info, detector.manifest):
            continue
        if instance_digests(scores(info.number)) == instances:
            if not options.allow_duplicate:
                raise duplicate_refused(info.number, count, options.stratify)
            return info.number
    return None


def read_parent(
    store: CalibrationStore, detector: Detector, version: int, scores: Scores | None = None
) -> Parent:
    """The version to append to with its scores; refused when missing or scored differently."""
    try:
        info = store.get_version(detector.model_hash, version)
    except VersionNotFound as error:
        raise NotFound(f"cannot append to calibration version {version}: it does not exist") from error
    if (reason := version_incompatibility(info, detector.manifest)) is not None:
        raise Conflict(f"cannot append: {reason}")
    table = store.load_scores(detector.model_hash, version) if scores is None else scores(version)
    return Parent(info, table)


def batch_name(requested: str | None, sha256: str) -> str:
    if requested is None:
        return f"upload-{sha256[:12]}"
    name = requested.strip()
    if not name or len(name) > 200 or any(ch in name for ch in "\r\n\t"):
        raise InvalidInput("name must be 1 to 200 printable characters on one line")
    return name


def check_group_labels(named: NamedBatch, parent: Parent | None) -> None:
    """stratify=group is refused at once (422) when no instance carries a group label."""
    inherited = parent is not None and any(block.has_groups for block in parent.scores.objects)
    if not inherited and not any(instance.group for instance in named.batch.instances):
        raise InvalidInput(
            "stratify=group needs group labels, and no annotation of the batch carries one:"
            ' add "group": "<label>" (a camera, a site) to the COCO annotations'
        )


def check_batch(
    named: NamedBatch, parent: Parent | None, *, dedupe: bool, max_rejected_share: float
) -> ValidatedBatch:
    """Refuse repeats (409, unless ``dedupe`` drops them) and too many rejected instances (422)."""
    batch: CocoBatch = named.batch
    prints = fingerprints(batch)
    sources = parent.info.source_batches if parent else ()
    table, number = (parent.scores, parent.info.number) if parent else (None, None)
    repeats = find_repeats(batch, prints, named.sha256, table, sources, number)
    if repeats and not dedupe:
        raise repeats_refused(repeats, batch.count)
    repeated = {(r.image_id, r.annotation_id) for r in repeats}
    keep = [(i.image_id, i.annotation_id) not in repeated for i in batch.instances]
    check_rejected_share(batch.rejected, batch.annotations, max_rejected_share)
    if not any(keep):
        raise InvalidInput("no instance of the batch is left to calibrate with once repeats are dropped")
    kept = replace(named, batch=replace(batch, instances=tuple(compress(batch.instances, keep))))
    return ValidatedBatch(kept, tuple(compress(prints, keep)), len(repeats), batch.rejected, parent)


def check_rejected_share(rejected: Sequence[Rejection], total: int, max_share: float) -> None:
    """422 listing the rejections when more than ``max_share`` of ``total`` instances were rejected."""
    if not rejected or len(rejected) <= max_share * total:
        return
    listed = capped([r.describe() for r in rejected], LISTED)
    raise InvalidInput(
        f"{len(rejected)} of {total} instances were rejected (first: {listed[0]}), more than the allowed"
        f" share of {max_share:g} (max_rejected_share, default {MAX_REJECTED_SHARE:g}); fix them, or"
        " allow a larger share to calibrate without them",
        errors=listed,
        extensions={"rejected": len(rejected), "instances": total},
    )


def duplicate_refused(version: int, count: int, stratify: frozenset[str] | None) -> Conflict:
    strata = "" if stratify is None else f" with the same strata ({describe_kinds(stratify)})"
    return Conflict(
        f"the batch would make a version equal to calibration version {version}: the same {count}"
        f" instances{strata}. Use version {version} (activate it, or pin calibration_version={version}),"
        " or upload with allow_duplicate=true and a reason if another copy is wanted",
        extensions={"duplicate_of": version},
    )


def repeats_refused(repeats: Sequence[Rejection], count: int) -> Conflict:
    """409 listing the repeats (anything with ``describe()``), or dropping them with dedupe."""
    listed = capped([r.describe() for r in repeats], LISTED)
    return Conflict(
        f"{len(repeats)} of {count} instances are already counted (first: {listed[0]}): each instance"
        " may enter a calibration once. Remove them, or drop them with dedupe=true (CLI: --dedupe)",
        errors=listed,
        extensions={"duplicates": len(repeats)},
    )
