"""Calibration versions: a new one made from validated batches, and a stored one activated (a
rollback when older than the active one), behind the guardrails, audited. A new version, its
activation, its job's success and their audit entries are one transaction.
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
from service.calibration.stratification import stored_kinds, version_strata
from service.detector.manifest import Manifest
from service.detector.session import Detector
from service.errors import Conflict, InvalidInput, NotFound
from service.infra.audit_trail import AuditTrail, Operator, written
from service.infra.metrics import CALIBRATION_INSTANCES

#: rejections listed in a job's result (the count is always given)
LISTED_REJECTIONS = 50


@dataclass(frozen=True)
class VersionRules:
    max_image_pixels: int
    min_instances: int


@dataclass(frozen=True)
class CalibrationOutcome:
    info: VersionInfo
    activated: bool
    comparison: Comparison | None
    summary: dict[str, Any]


@dataclass
class ScoredInstances:
    accumulator: ScoreAccumulator
    sources: list[SourceBatch]
    rejected: list[Rejection]
    added: int


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
    """Score ``batches`` (plus the ``parent``'s instances) and store them as one version."""
    accumulator, sources, rejected = ScoreAccumulator(), [], []
    if parent is not None:
        accumulator.extend(parent.scores)
        sources.extend(parent.info.source_batches)
    inherited = accumulator.count

    def counted(count: int) -> None:
        CALIBRATION_INSTANCES.inc(count)
        progress(count)

    for validated in batches:
        named, pixels = validated.named, rules.max_image_pixels
        rejected += validated.rejected
        rejected += score_batch(
            named.batch, named.name, detector, accumulator, pixels, counted, validated.fingerprints
        )
        sources.append(SourceBatch(named.name, named.sha256, named.batch.count))
    check_rejected_share(rejected, sum(v.named.batch.annotations for v in batches), options.rejected_share)
    if accumulator.count == inherited:
        raise InvalidInput("no instance of the batch could be scored; nothing was stored")
    scored = ScoredInstances(accumulator, sources, rejected, accumulator.count - inherited)
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
    """Store scored instances as one version, activated (``activate``) in its transaction unless the
    guardrails refuse and ``force`` does not override them; ``job_id``'s job succeeds in it too."""
    table = scored.accumulator.table()
    strata = version_strata(table, options.stratify)
    comparison, previous = None, None
    if options.activate:
        active = store.active_version(detector.model_hash)
        previous = active.version if active else None
        reference = None
        if previous is not None and _usable(store, detector, previous):  # an unusable one is no reference
            reference = store.load_scores(detector.model_hash, previous)
        comparison = compare(table, reference, detector.manifest, rules.min_instances, None, previous)
    activated = options.activate and (comparison.allowed or options.force)
    summary: dict[str, Any] = {
        "instances": table.n_instances,
        "added": scored.added,
        "activated": activated,
        "duplicates_dropped": duplicates_dropped,
        "rejected": len(scored.rejected),
        "rejections": [r.describe() for r in scored.rejected[:LISTED_REJECTIONS]],
    }
    if comparison is not None and not comparison.allowed:
        summary |= {"activation_problems": list(comparison.problems), "activation_forced": activated}
    entries = _audit_entries(audit, options, operator, summary, comparison, previous, activated)
    scoring = scoring_settings(detector.manifest)
    stored_strata = None if strata is None else strata.as_dict()
    # the store refuses a second version of the same content, unless a copy was asked for
    key = None if options.allow_duplicate else content_key(table, stored_kinds(stored_strata), scoring)
    new = NewVersion(
        model_hash=detector.model_hash,
        model_name=detector.manifest.name,
        normalization=scoring,
        source_batches=scored.sources,
        author=operator.name,
        note=options.note,
        parent_version=options.append_to,
        strata=stored_strata,
        content_key=key,
    )
    intent = ActivationIntent(operator.name, _activation_reason(options)) if activated else None
    job = JobCompletion(job_id, summary) if job_id else None
    try:
        info = store.create_version(new, table, activation=intent, job=job, audit=entries)
    except DuplicateVersion as error:  # a twin scored beside it, in any process, was stored first
        raise duplicate_refused(error.number, table.n_instances, options.stratify) from error
    written(*(entry if entry.version else replace(entry, version=info.number) for entry in entries))
    return CalibrationOutcome(info, activated, comparison, {**summary, "version": info.number})


def _usable(store: CalibrationStore, detector: Detector, version: int) -> bool:
    return version_incompatibility(store.get_version(detector.model_hash, version), detector.manifest) is None


def _audit_entries(
    audit: AuditTrail,
    options: UploadOptions,
    operator: Operator,
    summary: dict[str, Any],
    comparison: Comparison | None,
    previous: int | None,
    activated: bool,
) -> list[NewAuditEntry]:
    details = {k: summary[k] for k in ("instances", "added", "duplicates_dropped", "rejected")}
    stored = {"reason": options.note, "previous_version": options.append_to, "details": details}
    entries = [audit.entry(operator, "calibration", "stored", **stored)]
    if comparison is not None:
        outcome = "refused" if not activated else "forced" if not comparison.allowed else "activated"
        decision = {"previous_version": previous, "reason": _activation_reason(options)}
        entries.append(
            audit.entry(operator, "activation", outcome, **decision, details=_problems(comparison))
        )
    return entries


def _problems(comparison: Comparison) -> dict[str, list[str]]:
    return {"problems": list(comparison.problems)} if comparison.problems else {}


def _activation_reason(options: UploadOptions) -> str:
    return options.reason or "activated on creation"


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
    candidate, reference = registry.scores(version), None if against is None else registry.scores(against)
    return compare(candidate, reference, manifest, min_instances, version, against, epsilon, nonconformity)


def activate(
    registry: CalibrationRegistry,
    manifest: Manifest,
    audit: AuditTrail,
    request: ActivationRequest,
    min_instances: int,
) -> tuple[Activation, Comparison]:
    """Activate after comparing with the active version; 409 with the comparison when refused."""
    registry.check_usable(request.version)
    previous = registry.refresh_now()
    reference = previous if previous is not None and registry.incompatibility(previous) is None else None
    reference_args = (min_instances, REFERENCE_EPSILON, REFERENCE_NONCONFORMITY)
    comparison = comparison_with(registry, manifest, request.version, reference, *reference_args)
    if not comparison.allowed and not request.force:
        details = {"comparison": comparison.as_dict()}
        raise Conflict(refusal_detail(comparison), errors=list(comparison.problems), extensions=details)
    entry = audit.entry(
        request.operator,
        "rollback" if previous is not None and request.version < previous else "activation",
        "activated" if comparison.allowed else "forced",
        version=request.version,
        previous_version=previous,
        reason=request.reason,
        details=_problems(comparison),
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
