"""How the predict routes' bodies are documented (they are parsed by hand, in predict_input):
one image as JSON or multipart, and a batch as JSON or multipart."""

from __future__ import annotations

from typing import Any

from service.api.predict.predict_schemas import DOCUMENTED_BATCH_IMAGES

_SCHEMAS = "#/components/schemas/{model}"
_IMAGE = {"type": "string", "format": "binary", "description": "JPEG or PNG file"}
_JSON_PART = {"request": {"contentType": "application/json"}}


PREDICT_BODY: dict[str, Any] = {
    "required": True,
    "content": {
        "application/json": {"schema": {"$ref": _SCHEMAS.format(model="PredictJson")}},
        "multipart/form-data": {
            "schema": {
                "type": "object",
                "required": ["image", "request"],
                "properties": {
                    "image": _IMAGE,
                    "request": {"$ref": _SCHEMAS.format(model="PredictParameters")},
                },
            },
            "encoding": _JSON_PART,
        },
    },
}


def _batch_form() -> dict[str, Any]:
    indexes = range(DOCUMENTED_BATCH_IMAGES)
    parameters = {"$ref": _SCHEMAS.format(model="PredictParameters")}
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


BATCH_BODY: dict[str, Any] = {
    "required": True,
    "content": {
        "application/json": {"schema": {"$ref": _SCHEMAS.format(model="BatchJson")}},
        "multipart/form-data": {
            "schema": _batch_form(),
            "encoding": {f"request_{i}": _JSON_PART["request"] for i in range(DOCUMENTED_BATCH_IMAGES)},
        },
    },
}
