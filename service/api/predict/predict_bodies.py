"""How the predict routes' bodies (parsed by hand, in predict_input) are documented: one request content
type per operation, as every client generator can call it; the routes take either at run time."""

from __future__ import annotations

from typing import Any

from service.api.http.contract import SCHEMAS
from service.api.predict.predict_schemas import MAX_BATCH_IMAGES

_IMAGE = {"type": "string", "format": "binary", "description": "JPEG or PNG file"}
_PARAMETERS = {"$ref": SCHEMAS.format(model="PredictParameters")}
# A JSON part may come as a plain field or as a file (a Blob in FormData): both are read as JSON.
_JSON_PART = {"contentType": "application/json"}


# Examples are requests the service answers as they are (tests/api/test_document_examples.py sends
# each): a 16 x 16 grey PNG and a box inside it. Their object is the served model's first (contract.py).
_GREY_PNG = (
    "iVBORw0KGgoAAAANSUhEUgAAABAAAAAQCAIAAACQkWg2AAAANElEQVQoFZXBAQEAAAABIJ433QZV5FHkUeRR5FHkUeRR5FHkUeRR"
    "5FHkUeRR5FHkUeRR5DH7UhgRpIrbBwAAAABJRU5ErkJggg=="
)
EXAMPLE_INSTANCES = [{"object": "duck", "bbox": [4.0, 4.0, 8.0, 8.0]}]
# retain: the answer carries a prediction_id, which the feedback link takes to POST /v1/feedback
_PREDICT_EXAMPLE = {"image_base64": _GREY_PNG, "instances": EXAMPLE_INSTANCES, "retain": True}


def _json(model: str, example: dict[str, Any]) -> dict[str, Any]:
    schema = {"$ref": SCHEMAS.format(model=model)}
    return {"required": True, "content": {"application/json": {"schema": schema, "example": example}}}


def form_body(schema: dict[str, Any], json_parts: list[str], example: Any = None) -> dict[str, Any]:
    media = {"schema": schema, "encoding": {part: _JSON_PART for part in json_parts}}
    if example is not None:
        media["example"] = example
    return {"required": True, "content": {"multipart/form-data": media}}


def _batch_form() -> dict[str, Any]:
    """image_i and request_i together, said in words (schemathesis cannot generate from dependentRequired)."""
    indexes = range(MAX_BATCH_IMAGES)
    return {
        "type": "object",
        "description": "image_i and request_i for i = 0 .. n-1, n at most 16: a part without its twin, or"
        " a gap in the numbering, refuses the batch (422)",
        "required": ["image_0", "request_0"],
        "properties": {
            **{f"image_{i}": _IMAGE for i in indexes},
            **{f"request_{i}": _PARAMETERS for i in indexes},
        },
        "additionalProperties": False,
    }


PREDICT_JSON = _json("PredictJson", _PREDICT_EXAMPLE)
PREDICT_FORM = form_body(
    {
        "type": "object",
        "required": ["image", "request"],
        "properties": {"image": _IMAGE, "request": _PARAMETERS},
    },
    ["request"],
)
BATCH_JSON = _json("BatchJson", {"items": [_PREDICT_EXAMPLE, _PREDICT_EXAMPLE]})
BATCH_FORM = form_body(_batch_form(), [f"request_{i}" for i in range(MAX_BATCH_IMAGES)])
