"""Turn labeled batches into a new, immutable calibration version (and optionally activate it).

The version, its activation, the success of the job that produced it and their audit
entries are written in one transaction: a process killed at any moment leaves all of
them or none.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from typing import Any

from calibration_store import (
    ActivationIntent,
    CalibrationStore,
    JobCompletion,
    NewAuditEntry,
    NewVersion,
    ScoreTable,
    SourceBatch,
    VersionInfo,
    VersionNotFound,
)
from service.calibration.coco import NamedBatch, Rejection
from service.calibration.compatibility import scoring_settings, version_incompatibility
from service.calibration.guardrails import Comparison, compare
from service.calibration.intake import PreparedBatch, check_rejected_share
from service.calibration.scoring import ScoreAccumulator, score_batch
from service.calibration.stratification import VersionStrata, version_strata
from service.conformal.strata import DifficultySpec
from service.detector.session import Detector
from service.errors import Conflict, InvalidInput, NotFound
from service.runtime.audit_trail import AuditTrail, Operator, written
from service.runtime.metrics import CALIBRATION_INSTANCES

__all__ = ["CalibrationOptions", "CalibrationOutcome", "NamedBatch", "check_parent", "create_calibration"]

#: rejections listed in a job's result (the count is always given)
LISTED_REJECTIONS = 50
ACTIVATED_ON_CREATION = "activated on creation"


@dataclass(frozen=True)
class CalibrationOptions:
    operator: Operator
    note: str = ""
    append_to: int | None = None
    activate: bool = False
    force: bool = False
    reason: str = ""
    max_rejected_share: float = 0.0
    min_instances: int = 100
    stratify: frozenset[str] | None = None  # None: difficulty strata when the scores carry features
    difficulty: DifficultySpec = DifficultySpec()

    @property
    def activation_reason(self) -> str:
        return self.reason or ACTIVATED_ON_CREATION


@dataclass(frozen=True)
class CalibrationOutcome:
    info: VersionInfo
    activated: bool
    comparison: Comparison | None
    summary: dict[str, Any]


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
    batches: Sequence[PreparedBatch],
    options: CalibrationOptions,
    max_image_pixels: int,
    audit: AuditTrail,
    progress: Callable[[int], None] = lambda count: None,
    job_id: str | None = None,
) -> CalibrationOutcome:
    """Score ``batches`` (plus the parent's instances when appending) and store one version.

    With ``activate``, the new version is compared with the active one and activated in the
    same transaction unless the guardrails refuse it (then it is stored, not activated, and
    the refusal is in the summary), or ``force`` overrides them. With ``job_id``, that job is
    marked succeeded in the same transaction too.
    """
    scored = _score(store, detector, batches, options, max_image_pixels, progress)
    table = scored.accumulator.table()
    strata = version_strata(table, options.stratify, options.difficulty)
    comparison, previous = None, None
    if options.activate:
        comparison, previous = _compare_with_active(store, detector, table, options)
    activated = options.activate and (comparison.allowed or options.force)
    summary = _summary(table, scored, batches, activated, comparison)
    entries = _audit_entries(audit, options, summary, comparison, previous, activated)
    info = store.create_version(
        _new_version(detector, scored.sources, options, strata),
        table,
        activation=ActivationIntent(options.operator.name, options.activation_reason) if activated else None,
        job=JobCompletion(job_id, summary) if job_id else None,
        audit=entries,
    )
    written(*(entry if entry.version else replace(entry, version=info.number) for entry in entries))
    return CalibrationOutcome(info, activated, comparison, {**summary, "version": info.number})


@dataclass
class _Scored:
    accumulator: ScoreAccumulator
    sources: list[SourceBatch]
    rejected: list[Rejection]
    added: int


def _score(
    store: CalibrationStore,
    detector: Detector,
    batches: Sequence[PreparedBatch],
    options: CalibrationOptions,
    max_image_pixels: int,
    progress: Callable[[int], None],
) -> _Scored:
    """The parent's instances plus the batches' scored ones; refused if too many were rejected."""
    accumulator = ScoreAccumulator()
    sources: list[SourceBatch] = []
    if options.append_to is not None:
        parent = check_parent(store, detector, options.append_to)
        accumulator.extend(store.load_scores(detector.model_hash, options.append_to))
        sources.extend(parent.source_batches)
    inherited = accumulator.count

    def counted(count: int) -> None:
        CALIBRATION_INSTANCES.inc(count)
        progress(count)

    rejected: list[Rejection] = []
    for prepared in batches:
        named = prepared.named
        rejected.extend(prepared.rejected)
        rejected.extend(score_batch(named.batch, named.name, detector, accumulator, max_image_pixels, counted,
                                    prepared.fingerprints))  # fmt: skip
        sources.append(SourceBatch(named.name, named.sha256, named.batch.count))
    annotations = sum(p.named.batch.annotations for p in batches)
    check_rejected_share(rejected, annotations, options.max_rejected_share)
    if accumulator.count == inherited:
        raise InvalidInput("no instance of the batch could be scored; nothing was stored")
    return _Scored(accumulator, sources, rejected, accumulator.count - inherited)


def _compare_with_active(
    store: CalibrationStore, detector: Detector, table: ScoreTable, options: CalibrationOptions
) -> tuple[Comparison, int | None]:
    active = store.active_version(detector.model_hash)
    previous = active.version if active else None
    active_table = None
    if previous is not None and _usable(store, detector, previous):
        active_table = store.load_scores(detector.model_hash, previous)
    minimum = options.min_instances
    return compare(table, active_table, detector.manifest, minimum, active_version=previous), previous


def _usable(store: CalibrationStore, detector: Detector, version: int) -> bool:
    """Whether a version can serve the current manifest (an unusable one is no reference)."""
    return version_incompatibility(store.get_version(detector.model_hash, version), detector.manifest) is None


def _new_version(
    detector: Detector, sources: list[SourceBatch], options: CalibrationOptions, strata: VersionStrata | None
) -> NewVersion:
    return NewVersion(
        model_hash=detector.model_hash,
        model_name=detector.manifest.name,
        normalization=scoring_settings(detector.manifest),
        source_batches=sources,
        author=options.operator.name,
        note=options.note,
        parent_version=options.append_to,
        strata=None if strata is None else strata.as_dict(),
    )


def _summary(
    table: ScoreTable,
    scored: _Scored,
    batches: Sequence[PreparedBatch],
    activated: bool,
    comparison: Comparison | None,
) -> dict[str, Any]:
    """What a job reports (its result) and the CLI prints; the store adds the version."""
    summary: dict[str, Any] = {
        "instances": table.n_instances,
        "added": scored.added,
        "activated": activated,
        "duplicates_dropped": sum(p.repeats_dropped for p in batches),
        "rejected": len(scored.rejected),
        "rejections": [r.describe() for r in scored.rejected[:LISTED_REJECTIONS]],
    }
    if comparison is not None and not comparison.allowed:
        summary["activation_problems"] = list(comparison.problems)
        summary["activation_forced"] = activated
    return summary


def _audit_entries(
    audit: AuditTrail,
    options: CalibrationOptions,
    summary: dict[str, Any],
    comparison: Comparison | None,
    previous: int | None,
    activated: bool,
) -> list[NewAuditEntry]:
    """The version's entry and, when activation was asked, its decision (all in its transaction)."""
    details = {k: summary[k] for k in ("instances", "added", "duplicates_dropped", "rejected")}
    entries = [audit.entry(options.operator, "calibration", "stored", reason=options.note,
                           previous_version=options.append_to, details=details)]  # fmt: skip
    if comparison is not None:
        outcome = "refused" if not activated else "forced" if not comparison.allowed else "activated"
        problems = {"problems": list(comparison.problems)} if comparison.problems else {}
        entries.append(audit.entry(options.operator, "activation", outcome, previous_version=previous,
                                   reason=options.activation_reason, details=problems))  # fmt: skip
    return entries
