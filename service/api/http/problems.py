"""RFC 9457 problem+json for every error the API returns, each with the request's id."""

from __future__ import annotations

import logging

from fastapi import FastAPI, Request
from fastapi.exceptions import RequestValidationError
from fastapi.responses import JSONResponse
from pydantic import BaseModel, ConfigDict, Field
from starlette.exceptions import HTTPException as StarletteHTTPException
from starlette.routing import Match

from calibration_store import StoreFull, StoreUnavailable
from service.api.http.request_id import HEADER as REQUEST_ID_HEADER
from service.errors import InsufficientStorage, ServiceError, StoreUnreachable
from service.infra.logs import current_request

PROBLEM_JSON = "application/problem+json"
log = logging.getLogger(__name__)
_METHODS = ("DELETE", "GET", "HEAD", "PATCH", "POST", "PUT")
_INVALID = "Invalid input"  # as every other 422 (service.errors.InvalidInput)
_PREFIX = "Value error, "  # pydantic's, before the message of a validator's ValueError
_TITLES = {401: "Unauthorized", 403: "Forbidden", 404: "Not found", 405: "Method not allowed"}
# FastAPI's answer to a JSON body it cannot decode (not UTF-8, say): a 400 no operation documents.
_UNPARSED_BODY = "There was an error parsing the body"
_NO_ROUTE = "Not Found"  # Starlette's detail when no route matches the path
# pydantic's error types for a body that is not an object (bytes, a list, a string)
_NOT_AN_OBJECT = ("model_attributes_type", "dict_type", "model_type")


class Problem(BaseModel):
    """An RFC 9457 problem: what went wrong and what to fix (``application/problem+json``).

    Some problems carry more members (``comparison`` on a refused activation, ``duplicates``
    on a refused upload); they are described where they are sent."""

    model_config = ConfigDict(extra="allow")

    type: str = Field("about:blank", description="always about:blank: the status says the kind")
    title: str = Field(description="the status in words")
    status: int = Field(description="the HTTP status")
    detail: str = Field(description="what went wrong and what to fix")
    instance: str | None = Field(None, description="the request's path")
    errors: list[str] | None = Field(None, description="every problem found, when there are several")
    request_id: str | None = Field(
        None, description="the request's X-Request-ID: quote it when reporting a problem"
    )


def problem(
    status: int,
    title: str,
    detail: str,
    request: Request,
    errors: list | None = None,
    headers: dict[str, str] | None = None,
    extensions: dict | None = None,
) -> JSONResponse:
    body = {"type": "about:blank", "title": title, "status": status, "detail": detail}
    body["instance"] = request.url.path
    if errors:
        body["errors"] = errors
    body.update(extensions or {})
    context = current_request()
    if context is not None:
        body["request_id"] = context.request_id
        # The 500 handler answers outside RequestIdMiddleware, which sets the header on the rest.
        headers = {**(headers or {}), REQUEST_ID_HEADER: context.request_id}
    return JSONResponse(body, status_code=status, media_type=PROBLEM_JSON, headers=headers)


def _validation_errors(exc: RequestValidationError, content_type: str | None) -> list[str]:
    messages = []
    for error in exc.errors():
        if tuple(error.get("loc", ())) == ("body",) and error.get("type") in _NOT_AN_OBJECT:
            messages.append(_not_a_json_object(content_type))
            continue
        where = ".".join(str(part) for part in error.get("loc", ()) if part != "body")
        message = str(error.get("msg", "invalid")).removeprefix(_PREFIX)
        messages.append(f"{where}: {message}" if where else message)
    return messages


def _not_a_json_object(content_type: str | None) -> str:
    """A body that is not a JSON object: most often JSON sent without its Content-Type (curl -d
    alone sends application/x-www-form-urlencoded), which FastAPI does not read as JSON."""
    if content_type is None or "json" not in content_type.lower():
        sent = f"Content-Type: {content_type}" if content_type else "no Content-Type"
        return (
            f"the body must be JSON sent with 'Content-Type: application/json' (this request had {sent}):"
            " add -H 'Content-Type: application/json' to curl"
        )
    return "the body must be a JSON object: {...}"


def install_problem_handlers(app: FastAPI) -> None:
    @app.exception_handler(ServiceError)
    async def _service_error(request: Request, exc: ServiceError) -> JSONResponse:
        return problem(exc.status, exc.title, exc.detail, request, exc.errors, exc.headers, exc.extensions)

    @app.exception_handler(RequestValidationError)
    async def _invalid_request(request: Request, exc: RequestValidationError) -> JSONResponse:
        errors = _validation_errors(exc, request.headers.get("content-type"))
        detail = "The request does not match the schema: " + "; ".join(errors[:5])
        return problem(422, _INVALID, detail, request, errors)

    @app.exception_handler(StarletteHTTPException)
    async def _http_error(request: Request, exc: StarletteHTTPException) -> JSONResponse:
        if exc.status_code == 400 and exc.detail == _UNPARSED_BODY:
            detail = "The body is not JSON in UTF-8: send a JSON object"
            return problem(422, _INVALID, detail, request)
        if exc.status_code == 404 and exc.detail == _NO_ROUTE:
            return problem(404, _TITLES[404], _no_route(request), request, headers=exc.headers)
        headers = exc.headers
        if exc.status_code == 405:  # Starlette names only the methods of the first route that matched
            headers = {**(headers or {}), "Allow": ", ".join(allowed_methods(request))}
        title = _TITLES.get(exc.status_code, "Error")
        return problem(exc.status_code, title, str(exc.detail), request, headers=headers)

    @app.exception_handler(StoreUnavailable)  # and StoreFull, its kind
    async def _store_error(request: Request, exc: StoreUnavailable) -> JSONResponse:
        if isinstance(exc, StoreFull):
            error: ServiceError = InsufficientStorage(
                f"the calibration store's disk is full ({exc}): nothing was written;"
                " retry once space is freed"
            )
        else:
            error = StoreUnreachable(f"the calibration store is unreachable ({exc}): retry later")
        return await _service_error(request, error)

    @app.exception_handler(Exception)
    async def _unexpected(request: Request, exc: Exception) -> JSONResponse:
        log.exception("unhandled error on %s", request.url.path)
        return problem(500, "Internal error", "The server failed; the error was logged.", request)


def _no_route(request: Request) -> str:
    """Where to look instead: the same path under /v1 when some operation is there, and /docs."""
    path = request.url.path
    detail = f"no operation at {path}"
    under_v1 = {**request.scope, "path": "/v1" + path}
    routes = request.app.router.routes
    if not path.startswith("/v1/") and any(route.matches(under_v1)[0] is not Match.NONE for route in routes):
        detail += f": the API is under /v1, send {request.method} /v1{path}"
    return detail + "; every operation is listed at /docs"


def allowed_methods(request: Request) -> list[str]:
    """Every method some route serves at the request's path (asked route by route, method by method:
    included routers answer for their routes only as a whole)."""
    routes = request.app.router.routes
    return [
        method
        for method in _METHODS
        if any(route.matches({**request.scope, "method": method})[0] is Match.FULL for route in routes)
    ]
