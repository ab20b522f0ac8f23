"""Who a predict request comes from, for admission's cap per caller (``service.api.http.admission``).

Where predict tokens are on (``predict name:token`` lines in CKS_ADMIN_TOKENS_FILE), a caller is
the holder of the request's token (admin tokens predict too), and a request without a valid one is
refused with 401, a second later: an identity, unlike an address, cannot be spread over many
networks, and the pause slows a flood without tokens (and anyone guessing one). Otherwise a
caller is the request's address (behind CKS_TRUSTED_PROXIES, the client that X-Forwarded-For names,
as uvicorn's proxy headers give it).
"""

from __future__ import annotations

import asyncio

from starlette.requests import Request

from service.errors import ServiceError
from service.infra.operators import operator_named

#: How long a predict request without a valid token waits for its 401.
UNAUTHORIZED_DELAY_S = 1.0


class Unauthorized(ServiceError):
    status, title = 401, "Unauthorized"


class Callers:
    """The caller of a request, from its bearer token (``tokens``: token -> holder) or its address."""

    def __init__(self, tokens: dict[str, str]) -> None:
        self._tokens = tokens

    async def of(self, request: Request) -> str:
        if not self._tokens:
            return request.client.host if request.client else "unknown"
        scheme, _, token = request.headers.get("authorization", "").partition(" ")
        name = operator_named(self._tokens, token.strip()) if scheme.lower() == "bearer" else None
        if name is None:
            await asyncio.sleep(UNAUTHORIZED_DELAY_S)
            raise Unauthorized(
                "predict needs a predict token here: send 'Authorization: Bearer <token>' with a token of"
                " a 'predict name:token' line of CKS_ADMIN_TOKENS_FILE (or an admin token)",
                headers={"WWW-Authenticate": "Bearer"},
            )
        return f"token {name}"
