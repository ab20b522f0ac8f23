"""schemathesis hooks (loaded through SCHEMATHESIS_HOOKS): send generated bodies as application/zip."""

from __future__ import annotations

from typing import Any

import schemathesis
from schemathesis.transport.serialization import serialize_binary


@schemathesis.serializer("application/zip")
def zip_body(ctx: schemathesis.SerializationContext, value: Any) -> dict[str, Any]:
    return {"data": serialize_binary(value)}
