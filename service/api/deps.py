"""FastAPI dependencies: the service state and the admin bearer token check."""

from __future__ import annotations

import hmac
from typing import Annotated

from fastapi import Depends, HTTPException, Request
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer

from service.audit import Operator
from service.state import ServiceState

_bearer = HTTPBearer(auto_error=False, description="CKS_ADMIN_TOKEN, or a token of CKS_ADMIN_TOKENS_FILE")


# Dependencies are ``async def`` although they never await: FastAPI runs a plain ``def``
# dependency on its thread pool, a thread hop on every request.
async def get_state(request: Request) -> ServiceState:
    return request.app.state.service


State = Annotated[ServiceState, Depends(get_state)]


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
