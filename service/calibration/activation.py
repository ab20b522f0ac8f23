"""Activating a stored version (a rollback when it is older than the active one), behind the
guardrails, with the decision written to the audit trail."""

from __future__ import annotations

from dataclasses import dataclass

from calibration_store import Activation, VersionNotFound
from service.calibration.guardrails import (
    REFERENCE_EPSILON,
    REFERENCE_NONCONFORMITY,
    Comparison,
    compare,
    refusal_detail,
)
from service.calibration.registry import CalibrationRegistry
from service.detector.manifest import Manifest
from service.errors import Conflict, NotFound
from service.runtime.audit_trail import AuditTrail, Operator, written


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
    return compare(candidate, reference, manifest, min_instances, candidate_version=version,
                   active_version=against, epsilon=epsilon, nonconformity=nonconformity)  # fmt: skip


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
    comparison = comparison_with(registry, manifest, request.version, reference, min_instances,
                                 REFERENCE_EPSILON, REFERENCE_NONCONFORMITY)  # fmt: skip
    action = "rollback" if previous is not None and request.version < previous else "activation"
    problems = {"problems": list(comparison.problems)} if comparison.problems else {}
    if not comparison.allowed and not request.force:
        raise Conflict(refusal_detail(comparison), errors=list(comparison.problems),
                       extensions={"comparison": comparison.as_dict()})  # fmt: skip
    outcome = "activated" if comparison.allowed else "forced"
    entry = audit.entry(request.operator, action, outcome, version=request.version, previous_version=previous,
                        reason=request.reason, details=problems)  # fmt: skip
    try:
        activation = registry.store.activate(
            registry.model_hash, request.version, request.operator.name, request.reason, audit=[entry]
        )
    except VersionNotFound as error:
        raise NotFound(f"calibration version {request.version} does not exist for this model") from error
    written(entry)
    registry.refresh_now()
    return activation, comparison
