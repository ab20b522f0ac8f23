"""FastAPI dependencies: the service state, what the predict routes use, and the admin bearer
token check."""

from __future__ import annotations

import hmac
from concurrent.futures import Executor
from dataclasses import dataclass
from typing import Annotated

from fastapi import Depends, HTTPException, Request
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer

from service.api.request_body import BodyPace, read_limited_body
from service.prediction import Predictor
from service.runtime.admission import Admission
from service.runtime.audit_trail import Operator
from service.runtime.container import ServiceState

_bearer = HTTPBearer(auto_error=False, description="CKS_ADMIN_TOKEN, or a token of CKS_ADMIN_TOKENS_FILE")


# Dependencies are ``async def`` although they never await: FastAPI runs a plain ``def``
# dependency on its thread pool, a thread hop on every request.
async def get_state(request: Request) -> ServiceState:
    return request.app.state.service


State = Annotated[ServiceState, Depends(get_state)]


@dataclass(frozen=True)
class PredictParts:
    """What the predict routes use: the use case, admission, the CPU pool and the body limits."""

    predictor: Predictor
    admission: Admission
    pool: Executor
    max_request_bytes: int
    max_batch_images: int
    pace: BodyPace

    @classmethod
    def of(cls, state: ServiceState) -> PredictParts:
        settings = state.settings
        pace = BodyPace.from_settings(
            settings, settings.predict.request_read_timeout_seconds, "CKS_REQUEST_READ_TIMEOUT_SECONDS"
        )
        return cls(
            state.predictor,
            state.admission,
            state.cpu_pool,
            settings.predict.max_request_bytes,
            settings.predict.max_batch_images,
            pace,
        )

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
    state: State,
    credentials: Annotated[HTTPAuthorizationCredentials | None, Depends(_bearer)],
) -> Operator:
    """Let the request through only with a configured admin token (and a reachable store);
    returns the operator it names."""
    if not state.operators:
        raise HTTPException(
            403, "The admin API is disabled: set CKS_ADMIN_TOKEN or CKS_ADMIN_TOKENS_FILE to enable it."
        )
    name = None if credentials is None else _operator_name(state.operators, credentials.credentials)
    if name is None:
        raise HTTPException(
            401, "Send 'Authorization: Bearer <admin token>'.", headers={"WWW-Authenticate": "Bearer"}
        )
    state.registry.require_store()  # every admin call needs the store: 503 at once while it is away
    return Operator(name=name, client=request.client.host if request.client else "")


def _operator_name(operators: dict[str, str], presented: str) -> str | None:
    """Compare with every token in constant time each, so timing tells nothing about which matched."""
    found = None
    for token, name in operators.items():
        if hmac.compare_digest(presented.encode(), token.encode()):
            found = name
    return found


Admin = Annotated[Operator, Depends(require_admin)]
