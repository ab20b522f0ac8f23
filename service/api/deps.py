"""FastAPI dependencies: the service state and the admin bearer token check."""

from __future__ import annotations

import hmac
from typing import Annotated

from fastapi import Depends, HTTPException, Request
from fastapi.security import HTTPAuthorizationCredentials, HTTPBearer

from service.state import ServiceState

_bearer = HTTPBearer(auto_error=False, description="CKS_ADMIN_TOKEN")


# Dependencies are ``async def`` although they never await: FastAPI runs a plain ``def``
# dependency on its thread pool, a thread hop on every request.
async def get_state(request: Request) -> ServiceState:
    return request.app.state.service


State = Annotated[ServiceState, Depends(get_state)]


async def require_admin(
    state: State, credentials: Annotated[HTTPAuthorizationCredentials | None, Depends(_bearer)]
) -> str:
    """Let the request through only with the configured bearer token; returns who it was."""
    token = state.settings.admin_token
    if not token:
        raise HTTPException(403, "The admin API is disabled: set CKS_ADMIN_TOKEN to enable it.")
    if credentials is None or not hmac.compare_digest(credentials.credentials.encode(), token.encode()):
        raise HTTPException(
            401, "Send 'Authorization: Bearer <CKS_ADMIN_TOKEN>'.", headers={"WWW-Authenticate": "Bearer"}
        )
    return "admin"


Admin = Annotated[str, Depends(require_admin)]
