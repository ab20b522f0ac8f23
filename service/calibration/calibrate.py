"""Turn labeled batches into a new, immutable calibration version (and optionally activate it)."""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass

from calibration_store import CalibrationStore, NewVersion, SourceBatch, VersionInfo, VersionNotFound
from service.calibration.coco import CocoBatch
from service.calibration.compatibility import scoring_settings, version_incompatibility
from service.calibration.scoring import ScoreAccumulator, score_batch
from service.detector.runtime import Detector
from service.errors import Conflict, NotFound
from service.metrics import CALIBRATION_INSTANCES


@dataclass(frozen=True)
class NamedBatch:
    """A validated COCO batch with the name and sha256 it is recorded under."""

    name: str
    sha256: str
    batch: CocoBatch


@dataclass(frozen=True)
class CalibrationOptions:
    author: str
    note: str = ""
    append_to: int | None = None
    activate: bool = False


def check_parent(store: CalibrationStore, detector: Detector, version: int) -> VersionInfo:
    """The version to append to, refused when it is missing or was scored differently."""
    try:
        parent = store.get_version(detector.model_hash, version)
    except VersionNotFound as error:
        raise NotFound(f"cannot append to calibration version {version}: it does not exist") from error
    reason = version_incompatibility(parent, detector.manifest)
    if reason is not None:
        raise Conflict(f"cannot append: {reason}")
    return parent


def create_calibration(
    store: CalibrationStore,
    detector: Detector,
    batches: Sequence[NamedBatch],
    options: CalibrationOptions,
    max_image_pixels: int,
    progress: Callable[[int], None] = lambda count: None,
) -> VersionInfo:
    """Score ``batches`` (plus the parent's instances when appending), store one version."""
    accumulator = ScoreAccumulator()
    sources: list[SourceBatch] = []
    if options.append_to is not None:
        parent = check_parent(store, detector, options.append_to)
        accumulator.extend(store.load_scores(detector.model_hash, options.append_to))
        sources.extend(parent.source_batches)

    def counted(count: int) -> None:
        CALIBRATION_INSTANCES.inc(count)
        progress(count)

    for named in batches:
        score_batch(named.batch, named.name, detector, accumulator, max_image_pixels, counted)
        sources.append(SourceBatch(named.name, named.sha256, named.batch.count))
    new = NewVersion(
        model_hash=detector.model_hash,
        model_name=detector.manifest.name,
        normalization=scoring_settings(detector.manifest),
        source_batches=sources,
        author=options.author,
        note=options.note,
        parent_version=options.append_to,
    )
    info = store.create_version(new, accumulator.table())
    if options.activate:
        store.activate(detector.model_hash, info.number, options.author, "activated on creation")
    return info
