"""FastAPI dependencies: the service's long-lived parts, the predict routes' (``Predicting``), tokens."""

from __future__ import annotations

from collections.abc import Awaitable, Callable
from concurrent.futures import Executor
from dataclasses import dataclass
from typing import Annotated, Any

from fastapi import Depends, HTTPException, Request
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer

from calibration_store import CalibrationStore
from service.api.http.admission import Admission
from service.api.http.callers import Callers
from service.api.http.request_body import read_limited_body
from service.calibration.jobs import CalibrationJobs
from service.calibration.registry import CalibrationRegistry
from service.calibration.versions import VersionRules
from service.detector.manifest import Manifest
from service.detector.session import Detector
from service.errors import StoreUnreachable
from service.feedback.adaptive import AdaptiveSets
from service.feedback.live_coverage import LiveCoverageReader
from service.feedback.retention import Retention
from service.infra.audit_trail import AuditTrail, Operator
from service.infra.job_engine import JobRunner
from service.infra.operators import operator_named
from service.infra.settings import Settings
from service.monitoring.coverage_audits import CoverageAudits
from service.monitoring.drift_monitor import DriftMonitor
from service.prediction import Predictor

_CHALLENGE = {"WWW-Authenticate": "Bearer"}  # a 401's challenge
_bearer = HTTPBearer(auto_error=False, description="CKS_ADMIN_TOKEN, or a token of CKS_ADMIN_TOKENS_FILE")


# Dependencies are ``async def`` although they never await: FastAPI runs a plain ``def``
# dependency on its thread pool, a thread hop on every request.
def _part(name: str) -> Callable[[Request], Awaitable[Any]]:
    """A dependency giving one long-lived part of the service (an attribute of ServiceState)."""

    async def part(request: Request) -> Any:
        return getattr(request.app.state.service, name)

    part.__name__ = f"get_{name}"
    return part


Model = Annotated[Detector, Depends(_part("detector"))]
Registry = Annotated[CalibrationRegistry, Depends(_part("registry"))]
Store = Annotated[CalibrationStore, Depends(_part("store"))]
Jobs = Annotated[JobRunner, Depends(_part("jobs"))]
Calibrations = Annotated[CalibrationJobs, Depends(_part("calibrations"))]
Trail = Annotated[AuditTrail, Depends(_part("audit"))]
Audits = Annotated[CoverageAudits, Depends(_part("audits"))]
Drift = Annotated[DriftMonitor | None, Depends(_part("drift"))]
Config = Annotated[Settings, Depends(_part("settings"))]
Retaining = Annotated[Retention, Depends(_part("retention"))]
LiveCoverage = Annotated[LiveCoverageReader, Depends(_part("live_coverage"))]
Adaptive = Annotated[AdaptiveSets, Depends(_part("adaptive"))]
NewVersionRules = Annotated[VersionRules, Depends(_part("version_rules"))]


@dataclass(frozen=True)
class PredictParts:
    """What the predict routes use: the use case, admission, the CPU pool and the body limits."""

    predictor: Predictor
    admission: Admission
    pool: Executor
    max_request_bytes: int
    callers: Callers
    retention: Retention | None = None  # None: nothing is retained (no store to keep answers in)
    adaptive: AdaptiveSets | None = None  # None: no adaptive sets

    @property
    def manifest(self) -> Manifest:
        """The served model's: a request naming another object is told so with its other problems."""
        return self.predictor.detector.manifest

    async def arrive(self, request: Request) -> tuple[str, bytes]:
        """The caller (service.api.http.callers) and the body within CKS_MAX_REQUEST_BYTES, received once
        a place is in the caller's share (not worth receiving beyond it); no place is held meanwhile."""
        caller = await self.callers.of(request)
        await self.admission.wait_for_place(caller)
        return caller, await read_limited_body(request, self.max_request_bytes, "CKS_MAX_REQUEST_BYTES")


async def get_predict_parts(request: Request) -> PredictParts:
    return request.app.state.predict_parts


Predicting = Annotated[PredictParts, Depends(get_predict_parts)]


def _token_holder(tokens: str, kind: str, disabled: str) -> Callable[..., Awaitable[Operator]]:
    """A dependency giving the operator a bearer token of ``tokens`` (a ServiceState attribute) names:
    403 ``disabled`` with no tokens, 401 without one of them, 503 while the store is away."""

    async def holder(
        request: Request,
        registry: Registry,
        trail: Trail,
        credentials: Annotated[HTTPAuthorizationCredentials | None, Depends(_bearer)],
    ) -> Operator:
        held = getattr(request.app.state.service, tokens)
        if not held:
            raise HTTPException(403, disabled)
        name = None if credentials is None else operator_named(held, credentials.credentials)
        if name is None:
            raise HTTPException(401, _unauthorized(request, credentials, kind), headers=_CHALLENGE)
        operator = Operator(name=name, client=request.client.host if request.client else "")
        try:
            registry.require_store()  # every such call needs the store: 503 at once while it is away
        except StoreUnreachable as error:  # audited once the store is back (the outbox keeps it)
            call = {"method": request.method, "path": request.url.path}
            details = {"status": 503, "detail": error.detail, **call}
            trail.record_later(operator, "admin", "refused", details=details)
            raise
        return operator

    return holder


def _unauthorized(request: Request, credentials: HTTPAuthorizationCredentials | None, kind: str) -> str:
    """No header, no ``Bearer `` before the token, or a token not a ``kind`` (never echoed)."""
    if credentials is not None:
        article = "an" if kind[0] in "aeiou" else "a"
        return (
            f"The bearer token is not {article} {kind}: send CKS_ADMIN_TOKEN's value, or a token of"
            f" CKS_ADMIN_TOKENS_FILE, as 'Authorization: Bearer <{kind}>'."
        )
    if "authorization" in request.headers:
        return (
            "The Authorization header does not start with 'Bearer ': write it as"
            f" 'Authorization: Bearer <{kind}>' (the word Bearer, a space, then the token)."
        )
    path = "the admin API needs" if kind == "admin token" else "feedback needs"
    return f"No Authorization header: {path} 'Authorization: Bearer <{kind}>'."


_ADMIN_DISABLED = "The admin API is disabled: set CKS_ADMIN_TOKEN or CKS_ADMIN_TOKENS_FILE to enable it."
Admin = Annotated[Operator, Depends(_token_holder("operators", "admin token", _ADMIN_DISABLED))]
# What Admin answers, documented on every admin operation.
ADMIN_RESPONSES: dict[int | str, dict[str, Any]] = {
    401: {"description": "No token, or not an admin token: send 'Authorization: Bearer <admin token>'"},
    403: {"description": "The admin API is disabled (no CKS_ADMIN_TOKEN nor CKS_ADMIN_TOKENS_FILE)"},
    503: {"description": "The calibration store is unreachable (with Retry-After)"},
}


_FEEDBACK_DISABLED = (
    "Feedback is disabled: give its senders tokens ('feedback name:token' lines in"
    " CKS_ADMIN_TOKENS_FILE, or an admin token)"
)
FeedbackSender = Annotated[
    Operator, Depends(_token_holder("feedback_senders", "feedback or admin token", _FEEDBACK_DISABLED))
]
FEEDBACK_RESPONSES: dict[int | str, dict[str, Any]] = {
    401: {"description": "No token, or neither a feedback nor an admin token"},
    403: {"description": "Feedback is disabled (no admin token and no 'feedback name:token' line)"},
    503: ADMIN_RESPONSES[503],
}
