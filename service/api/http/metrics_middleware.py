"""ASGI middleware that counts, times and logs every request under its route template."""

from __future__ import annotations

import logging
import time

from starlette.types import Message, Receive, Scope, Send

from service.api.http.http_middleware import HttpMiddleware
from service.infra.logs import ACCESS_LOGGER, current_request, log_fields
from service.infra.metrics import LATENCY, REQUESTS

access_log = logging.getLogger(ACCESS_LOGGER)


class MetricsMiddleware(HttpMiddleware):
    """Counts and times every request under its route template (not the raw path), and logs
    its access line (CKS_ACCESS_LOG) with the raw path, the request id and, for a prediction,
    the calibration version that answered."""

    async def handle(self, scope: Scope, receive: Receive, send: Send) -> None:
        start = time.perf_counter()
        status = {"code": 500}

        async def send_with_status(message: Message) -> None:
            if message["type"] == "http.response.start":
                status["code"] = message["status"]
            await send(message)

        try:
            await self.app(scope, receive, send_with_status)
        finally:
            elapsed = time.perf_counter() - start
            path = getattr(scope.get("route"), "path", None) or "unmatched"
            method = scope.get("method", "GET")
            REQUESTS.labels(method, path, str(status["code"])).inc()
            LATENCY.labels(method, path).observe(elapsed)
            if access_log.isEnabledFor(logging.INFO):
                _log_access(scope, method, status["code"], elapsed)


def _log_access(scope: Scope, method: str, status: int, elapsed: float) -> None:
    request, client = current_request(), scope.get("client")
    fields = {"method": method, "path": scope.get("path", ""), "status": status}
    fields["duration_ms"] = round(elapsed * 1000, 1)
    fields["calibration_version"] = request.calibration_version if request else None
    fields["client"] = client[0] if client else None
    log_fields(access_log, "access", fields)
