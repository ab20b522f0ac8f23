"""How the predict routes' bodies are documented (they are parsed by hand, in predict_input): one
request content type per operation, as every client generator can call it. One image as JSON
(``PREDICT_JSON``) or as multipart (``PREDICT_FORM``), a batch as JSON (``BATCH_JSON``) or as
multipart (``BATCH_FORM``). The routes take either type at run time (docs/api.md says which)."""

from __future__ import annotations

from typing import Any

from service.api.predict.predict_schemas import ITEM_ANSWERED_ALONE, MAX_BATCH_IMAGES

_SCHEMAS = "#/components/schemas/{model}"
_IMAGE = {"type": "string", "format": "binary", "description": "JPEG or PNG file"}
# A JSON part may come as a plain field or as a file (a Blob in FormData): both are read as JSON.
_JSON_PART = {"contentType": "application/json"}


def _json(model: str) -> dict[str, Any]:
    schema = {"$ref": _SCHEMAS.format(model=model)}
    return {"required": True, "content": {"application/json": {"schema": schema}}}


def _form(schema: dict[str, Any], json_parts: list[str]) -> dict[str, Any]:
    encoding = {part: _JSON_PART for part in json_parts}
    return {"required": True, "content": {"multipart/form-data": {"schema": schema, "encoding": encoding}}}


def _batch_form() -> dict[str, Any]:
    indexes = range(MAX_BATCH_IMAGES)
    parameters = {
        "anyOf": [{"$ref": _SCHEMAS.format(model="PredictParameters")}, {"description": ITEM_ANSWERED_ALONE}]
    }
    return {
        "type": "object",
        "description": "image_i and request_i for i = 0 .. n-1, n at most CKS_MAX_BATCH_IMAGES (default 16)",
        "required": ["image_0", "request_0"],
        "properties": {
            **{f"image_{i}": _IMAGE for i in indexes},
            **{f"request_{i}": parameters for i in indexes},
        },
        "additionalProperties": False,
    }


PREDICT_JSON = _json("PredictJson")
PREDICT_FORM = _form(
    {
        "type": "object",
        "required": ["image", "request"],
        "properties": {"image": _IMAGE, "request": {"$ref": _SCHEMAS.format(model="PredictParameters")}},
    },
    ["request"],
)
BATCH_JSON = _json("BatchJson")
BATCH_FORM = _form(_batch_form(), [f"request_{i}" for i in range(MAX_BATCH_IMAGES)])
