"""FastAPI dependencies: each long-lived part a route uses (``Registry``, ``Store``, ...), what
the predict routes use (``Predicting``), and the admin bearer token check (``Admin``)."""

from __future__ import annotations

from collections.abc import Awaitable, Callable
from concurrent.futures import Executor
from dataclasses import dataclass
from typing import Annotated, Any

from fastapi import Depends, HTTPException, Request
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer

from calibration_store import CalibrationStore
from service.api.http.admission import Admission
from service.api.http.clients import ClientKeys
from service.api.http.request_body import BodyPace, read_limited_body
from service.calibration.jobs import CalibrationJobs, JobRunner
from service.calibration.registry import CalibrationRegistry
from service.detector.manifest import Manifest
from service.detector.session import Detector
from service.infra.audit_trail import AuditTrail, Operator
from service.infra.operators import operator_named
from service.infra.settings import Settings
from service.monitoring.coverage_audits import CoverageAudits
from service.monitoring.drift_monitor import DriftMonitor
from service.prediction import Predictor

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
Operators = Annotated[dict[str, str], Depends(_part("operators"))]


@dataclass(frozen=True)
class PredictParts:
    """What the predict routes use: the use case, admission, the CPU pool and the body limits."""

    predictor: Predictor
    admission: Admission
    pool: Executor
    max_request_bytes: int
    max_batch_images: int
    pace: BodyPace
    clients: ClientKeys

    @property
    def manifest(self) -> Manifest:
        """The served model's: a request naming another object is told so with its other problems."""
        return self.predictor.detector.manifest

    def client_of(self, request: Request) -> str:
        """Whose share of the admission places this request takes (service.api.http.clients)."""
        return self.clients.of(request.client.host if request.client else None, request.headers)

    async def receive(self, request: Request) -> bytes:
        """The body within CKS_MAX_REQUEST_BYTES, paced, its bytes counted against
        CKS_MAX_RECEIVING_BYTES while it arrives."""
        with self.admission.receiving() as count:
            return await read_limited_body(
                request, self.max_request_bytes, "CKS_MAX_REQUEST_BYTES", self.pace, count
            )


async def get_predict_parts(request: Request) -> PredictParts:
    return request.app.state.predict_parts


Predicting = Annotated[PredictParts, Depends(get_predict_parts)]


async def require_admin(
    request: Request,
    operators: Operators,
    registry: Registry,
    credentials: Annotated[HTTPAuthorizationCredentials | None, Depends(_bearer)],
) -> Operator:
    """Let the request through only with a configured admin token (and a reachable store);
    returns the operator it names."""
    if not operators:
        raise HTTPException(
            403, "The admin API is disabled: set CKS_ADMIN_TOKEN or CKS_ADMIN_TOKENS_FILE to enable it."
        )
    name = None if credentials is None else operator_named(operators, credentials.credentials)
    if name is None:
        raise HTTPException(401, _unauthorized(request, credentials), headers={"WWW-Authenticate": "Bearer"})
    registry.require_store()  # every admin call needs the store: 503 at once while it is away
    return Operator(name=name, client=request.client.host if request.client else "")


def _unauthorized(request: Request, credentials: HTTPAuthorizationCredentials | None) -> str:
    """Which of the three mistakes it is: no header, no ``Bearer `` before the token, or a token
    that is not an admin token (never echoed)."""
    if credentials is not None:
        return (
            "The bearer token is not an admin token: send CKS_ADMIN_TOKEN's value, or a token of"
            " CKS_ADMIN_TOKENS_FILE, as 'Authorization: Bearer <admin token>'."
        )
    if "authorization" in request.headers:
        return (
            "The Authorization header does not start with 'Bearer ': write it as"
            " 'Authorization: Bearer <admin token>' (the word Bearer, a space, then the token)."
        )
    return "No Authorization header: the admin API needs 'Authorization: Bearer <admin token>'."


Admin = Annotated[Operator, Depends(require_admin)]
# What require_admin answers, documented on every admin operation.
ADMIN_RESPONSES: dict[int | str, dict[str, Any]] = {
    401: {"description": "No token, or not an admin token: send 'Authorization: Bearer <admin token>'"},
    403: {"description": "The admin API is disabled (no CKS_ADMIN_TOKEN nor CKS_ADMIN_TOKENS_FILE)"},
    503: {"description": "The calibration store is unreachable (with Retry-After)"},
}
