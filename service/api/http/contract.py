"""The OpenAPI document as generated clients read it: FastAPI's, plus the bodies parsed by hand, the
``Problem`` body of every status from 400 (routes describe them in words only), the request id every
operation takes, the headers sent, and the served model's object names (the enum of an instance's
``object``; the examples name the first, so that each is a request the service answers)."""

from __future__ import annotations

import copy
from collections.abc import Callable
from typing import Any

from fastapi import FastAPI
from pydantic import BaseModel

from service.api.http.problems import PROBLEM_JSON, Problem

SCHEMAS = "#/components/schemas/{model}"
HEADERS = "#/components/headers/{name}"
_HEADERS: dict[str, dict[str, Any]] = {
    "X-Request-ID": {
        "description": "the request's id: the caller's X-Request-ID (1 to 128 visible ASCII characters)"
        " or one the service made up; quote it when reporting a problem",
        "required": True,
        "schema": {"type": "string"},
    },
    "Retry-After": {
        "description": "seconds to wait before sending the request again",
        "schema": {"type": "integer", "minimum": 0},
    },
    "Location": {"description": "where to follow the job", "required": True, "schema": {"type": "string"}},
    "WWW-Authenticate": {"description": "Bearer", "required": True, "schema": {"type": "string"}},
}
# The statuses whose answers carry each header besides X-Request-ID.
_HEADER_STATUSES = {"Retry-After": {"429", "503"}, "Location": {"202"}, "WWW-Authenticate": {"401"}}
_VALIDATION_DEFAULT = "Validation Error"
# Every operation takes the caller's request id (RequestIdMiddleware): any string is accepted.
_REQUEST_ID_PARAMETER = {
    "name": "X-Request-ID",
    "in": "header",
    "required": False,
    "description": "your id for this request, echoed in the answer's X-Request-ID, its problem's"
    " request_id and the service's log lines: kept if 1 to 128 visible ASCII characters, else"
    " replaced by one the service makes up",
    "schema": {"type": "string"},
}


def install_contract(
    app: FastAPI, parsed_bodies: tuple[type[BaseModel], ...], object_names: Callable[[], tuple[str, ...]]
) -> None:
    """Make ``app.openapi()`` return the completed document (built once, then cached)."""
    generate = app.openapi

    def openapi() -> dict[str, Any]:
        if app.openapi_schema is None:
            document = completed(generate(), (Problem, *parsed_bodies))
            names = list(object_names())
            document["components"]["schemas"]["InstanceIn"]["properties"]["object"]["enum"] = names
            # the examples' instances (module constants, shared with other apps) name its first object
            document["paths"] = _named(copy.deepcopy(document["paths"]), names[0])
            app.openapi_schema = document
        return app.openapi_schema

    app.openapi = openapi  # type: ignore[method-assign]


def completed(document: dict[str, Any], models: tuple[type[BaseModel], ...]) -> dict[str, Any]:
    document.setdefault("components", {})["headers"] = _HEADERS
    components = document["components"].setdefault("schemas", {})
    for model in models:
        schema = model.model_json_schema(ref_template=SCHEMAS)
        components.update(schema.pop("$defs", {}))
        components[model.__name__] = schema
    for operations in document["paths"].values():
        for operation in operations.values():
            operation.setdefault("parameters", []).append(_REQUEST_ID_PARAMETER)
            for status, response in operation["responses"].items():
                _complete(status, response)
    for unused in ("HTTPValidationError", "ValidationError"):  # FastAPI's 422 body, never sent
        components.pop(unused, None)
    return document


def _named(value: Any, name: str) -> Any:
    """``value`` with every instance (an object with a bbox) of object ``name``."""
    if isinstance(value, dict):
        if "object" in value and "bbox" in value:
            value["object"] = name
        for member in value.values():
            _named(member, name)
    elif isinstance(value, list):
        for item in value:
            _named(item, name)
    return value


def _complete(status: str, response: dict[str, Any]) -> None:
    if int(status) >= 400:
        response["content"] = {PROBLEM_JSON: {"schema": {"$ref": SCHEMAS.format(model="Problem")}}}
        if response.get("description") == _VALIDATION_DEFAULT:
            response["description"] = "The request does not match the schema: `errors` lists every problem"
    headers = response.setdefault("headers", {})
    headers["X-Request-ID"] = {"$ref": HEADERS.format(name="X-Request-ID")}
    for name, statuses in _HEADER_STATUSES.items():
        if status in statuses:
            headers[name] = {"$ref": HEADERS.format(name=name)}
