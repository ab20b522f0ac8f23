"""Calibration versions: a new, immutable one made from validated batches (and optionally
activated), and a stored one activated (a rollback when it is older than the active one),
both behind the guardrails, with their decisions in the audit trail.

A new version, its activation, the success of the job that produced it and their audit
entries are written in one transaction: a process killed at any moment leaves all of
them or none.
"""

from __future__ import annotations

from collections.abc import Callable, Sequence
from dataclasses import dataclass, replace
from typing import Any

from calibration_store import (
    Activation,
    ActivationIntent,
    CalibrationStore,
    DuplicateVersion,
    JobCompletion,
    NewAuditEntry,
    NewVersion,
    ScoreTable,
    SourceBatch,
    VersionInfo,
    VersionNotFound,
)
from service.calibration.coco import Rejection
from service.calibration.compatibility import scoring_settings, version_incompatibility
from service.calibration.fingerprints import content_key
from service.calibration.guardrails import (
    REFERENCE_EPSILON,
    REFERENCE_NONCONFORMITY,
    Comparison,
    compare,
    refusal_detail,
)
from service.calibration.intake import (
    Parent,
    UploadOptions,
    ValidatedBatch,
    check_rejected_share,
    duplicate_refused,
)
from service.calibration.registry import CalibrationRegistry
from service.calibration.scoring import ScoreAccumulator, score_batch
from service.calibration.stratification import VersionStrata, stored_kinds, version_strata
from service.conformal.strata import DifficultySpec
from service.detector.manifest import Manifest
from service.detector.session import Detector
from service.errors import Conflict, InvalidInput, NotFound
from service.infra.audit_trail import AuditTrail, Operator, written
from service.infra.metrics import CALIBRATION_INSTANCES

#: rejections listed in a job's result (the count is always given)
LISTED_REJECTIONS = 50
ACTIVATED_ON_CREATION = "activated on creation"


@dataclass(frozen=True)
class VersionRules:
    """What every new version is held to (from the settings)."""

    max_image_pixels: int
    min_instances: int
    max_rejected_share: float
    difficulty: DifficultySpec = DifficultySpec()


@dataclass(frozen=True)
class CalibrationOutcome:
    info: VersionInfo
    activated: bool
    comparison: Comparison | None
    summary: dict[str, Any]


def create_version(
    store: CalibrationStore,
    detector: Detector,
    batches: Sequence[ValidatedBatch],
    parent: Parent | None,
    options: UploadOptions,
    operator: Operator,
    rules: VersionRules,
    audit: AuditTrail,
    progress: Callable[[int], None] = lambda count: None,
    job_id: str | None = None,
) -> CalibrationOutcome:
    """Score ``batches`` (plus the ``parent``'s instances when appending) and store one version.

    With ``activate``, the new version is compared with the active one and activated in the
    same transaction unless the guardrails refuse it (then it is stored, not activated, and
    the refusal is in the summary), or ``force`` overrides them. With ``job_id``, that job is
    marked succeeded in the same transaction too.
    """
    share = options.rejected_share(rules.max_rejected_share)
    scored = _score(detector, batches, parent, share, rules.max_image_pixels, progress)
    dropped = sum(v.repeats_dropped for v in batches)
    return store_scored_version(store, detector, scored, dropped, options, operator, rules, audit, job_id)


def store_scored_version(
    store: CalibrationStore,
    detector: Detector,
    scored: ScoredInstances,
    duplicates_dropped: int,
    options: UploadOptions,
    operator: Operator,
    rules: VersionRules,
    audit: AuditTrail,
    job_id: str | None = None,
) -> CalibrationOutcome:
    """Store scored instances as one version, behind the guardrails (see ``create_version``): also
    the way labelled feedback becomes a version (service.feedback.field_calibration)."""
    table = scored.accumulator.table()
    strata = version_strata(table, options.stratify, rules.difficulty)
    comparison, previous = None, None
    if options.activate:
        comparison, previous = _compare_with_active(store, detector, table, rules.min_instances)
    activated = options.activate and (comparison.allowed or options.force)
    summary = _summary(table, scored, duplicates_dropped, activated, comparison)
    entries = _audit_entries(audit, options, operator, summary, comparison, previous, activated)
    try:
        info = store.create_version(
            _new_version(detector, table, scored.sources, options, operator, strata),
            table,
            activation=ActivationIntent(operator.name, _activation_reason(options)) if activated else None,
            job=JobCompletion(job_id, summary) if job_id else None,
            audit=entries,
        )
    except DuplicateVersion as error:  # a twin scored beside it, in any process, was stored first
        raise duplicate_refused(error.number, table.n_instances, options.stratify) from error
    written(*(entry if entry.version else replace(entry, version=info.number) for entry in entries))
    return CalibrationOutcome(info, activated, comparison, {**summary, "version": info.number})


@dataclass
class ScoredInstances:
    """Instances scored for a new version: the parent's and the new, their sources, the rejected."""

    accumulator: ScoreAccumulator
    sources: list[SourceBatch]
    rejected: list[Rejection]
    added: int


def _score(
    detector: Detector,
    batches: Sequence[ValidatedBatch],
    parent: Parent | None,
    max_rejected_share: float,
    max_image_pixels: int,
    progress: Callable[[int], None],
) -> ScoredInstances:
    """The parent's instances plus the batches' scored ones; refused if too many were rejected."""
    accumulator = ScoreAccumulator()
    sources: list[SourceBatch] = []
    if parent is not None:
        accumulator.extend(parent.scores)
        sources.extend(parent.info.source_batches)
    inherited = accumulator.count

    def counted(count: int) -> None:
        CALIBRATION_INSTANCES.inc(count)
        progress(count)

    rejected: list[Rejection] = []
    for validated in batches:
        named = validated.named
        rejected.extend(validated.rejected)
        prints = validated.fingerprints
        rejected.extend(
            score_batch(named.batch, named.name, detector, accumulator, max_image_pixels, counted, prints)
        )
        sources.append(SourceBatch(named.name, named.sha256, named.batch.count))
    annotations = sum(v.named.batch.annotations for v in batches)
    check_rejected_share(rejected, annotations, max_rejected_share)
    if accumulator.count == inherited:
        raise InvalidInput("no instance of the batch could be scored; nothing was stored")
    return ScoredInstances(accumulator, sources, rejected, accumulator.count - inherited)


def _compare_with_active(
    store: CalibrationStore, detector: Detector, table: ScoreTable, min_instances: int
) -> tuple[Comparison, int | None]:
    active = store.active_version(detector.model_hash)
    previous = active.version if active else None
    active_table = None
    if previous is not None and _usable(store, detector, previous):
        active_table = store.load_scores(detector.model_hash, previous)
    return compare(table, active_table, detector.manifest, min_instances, active_version=previous), previous


def _usable(store: CalibrationStore, detector: Detector, version: int) -> bool:
    """Whether a version can serve the current manifest (an unusable one is no reference)."""
    return version_incompatibility(store.get_version(detector.model_hash, version), detector.manifest) is None


def _new_version(
    detector: Detector,
    table: ScoreTable,
    sources: list[SourceBatch],
    options: UploadOptions,
    operator: Operator,
    strata: VersionStrata | None,
) -> NewVersion:
    """The version to store; one the store refuses if it holds the same content, unless a copy
    was asked for (``allow_duplicate``)."""
    scoring = scoring_settings(detector.manifest)
    stored_strata = None if strata is None else strata.as_dict()
    key = None if options.allow_duplicate else content_key(table, stored_kinds(stored_strata), scoring)
    return NewVersion(
        model_hash=detector.model_hash,
        model_name=detector.manifest.name,
        normalization=scoring,
        source_batches=sources,
        author=operator.name,
        note=options.note,
        parent_version=options.append_to,
        strata=stored_strata,
        content_key=key,
    )


def _summary(
    table: ScoreTable,
    scored: ScoredInstances,
    duplicates_dropped: int,
    activated: bool,
    comparison: Comparison | None,
) -> dict[str, Any]:
    """What a job reports (its result) and the CLI prints; the store adds the version."""
    summary: dict[str, Any] = {
        "instances": table.n_instances,
        "added": scored.added,
        "activated": activated,
        "duplicates_dropped": duplicates_dropped,
        "rejected": len(scored.rejected),
        "rejections": [r.describe() for r in scored.rejected[:LISTED_REJECTIONS]],
    }
    if comparison is not None and not comparison.allowed:
        summary["activation_problems"] = list(comparison.problems)
        summary["activation_forced"] = activated
    return summary


def _audit_entries(
    audit: AuditTrail,
    options: UploadOptions,
    operator: Operator,
    summary: dict[str, Any],
    comparison: Comparison | None,
    previous: int | None,
    activated: bool,
) -> list[NewAuditEntry]:
    """The version's entry and, when activation was asked, its decision (all in its transaction)."""
    details = {k: summary[k] for k in ("instances", "added", "duplicates_dropped", "rejected")}
    parent = options.append_to
    entries = [
        audit.entry(
            operator, "calibration", "stored", reason=options.note, previous_version=parent, details=details
        )
    ]
    if comparison is not None:
        outcome = "refused" if not activated else "forced" if not comparison.allowed else "activated"
        problems = {"problems": list(comparison.problems)} if comparison.problems else {}
        reason = _activation_reason(options)
        decision = audit.entry(
            operator, "activation", outcome, previous_version=previous, reason=reason, details=problems
        )
        entries.append(decision)
    return entries


def _activation_reason(options: UploadOptions) -> str:
    return options.reason or ACTIVATED_ON_CREATION


# -- activating a stored version ----------------------------------------------------


@dataclass(frozen=True)
class ActivationRequest:
    version: int
    operator: Operator
    reason: str = ""
    force: bool = False


def comparison_with(
    registry: CalibrationRegistry,
    manifest: Manifest,
    version: int,
    against: int | None,
    min_instances: int,
    epsilon: float,
    nonconformity: str,
) -> Comparison:
    """Version ``version`` against ``against`` (None: nothing); 404 for a missing version."""
    candidate = registry.scores(version)
    reference = None if against is None else registry.scores(against)
    return compare(
        candidate,
        reference,
        manifest,
        min_instances,
        candidate_version=version,
        active_version=against,
        epsilon=epsilon,
        nonconformity=nonconformity,
    )


def activate(
    registry: CalibrationRegistry,
    manifest: Manifest,
    audit: AuditTrail,
    request: ActivationRequest,
    min_instances: int,
) -> tuple[Activation, Comparison]:
    """Activate after comparing with the active version; 409 with the comparison when refused
    (the caller audits refusals; an activation is audited in its own transaction)."""
    registry.check_usable(request.version)
    previous = registry.refresh_now()
    reference = previous if previous is not None and registry.incompatibility(previous) is None else None
    comparison = comparison_with(
        registry,
        manifest,
        request.version,
        reference,
        min_instances,
        REFERENCE_EPSILON,
        REFERENCE_NONCONFORMITY,
    )
    action = "rollback" if previous is not None and request.version < previous else "activation"
    problems = {"problems": list(comparison.problems)} if comparison.problems else {}
    if not comparison.allowed and not request.force:
        raise Conflict(
            refusal_detail(comparison),
            errors=list(comparison.problems),
            extensions={"comparison": comparison.as_dict()},
        )
    outcome = "activated" if comparison.allowed else "forced"
    entry = audit.entry(
        request.operator,
        action,
        outcome,
        version=request.version,
        previous_version=previous,
        reason=request.reason,
        details=problems,
    )
    try:
        activation = registry.store.activate(
            registry.model_hash, request.version, request.operator.name, request.reason, audit=[entry]
        )
    except VersionNotFound as error:
        raise NotFound(f"calibration version {request.version} does not exist for this model") from error
    written(entry)
    registry.refresh_now()
    return activation, comparison
