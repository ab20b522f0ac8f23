"""The FastAPI application factory."""

from __future__ import annotations

import gc
from collections.abc import AsyncIterator
from contextlib import asynccontextmanager

from fastapi import FastAPI
from fastapi.routing import APIRoute
from fastapi_offline import FastAPIOffline
from starlette.types import Message, Receive, Scope, Send

from service import __version__
from service.api.admin import audit_routes, calibration_routes
from service.api.deps import PredictParts
from service.api.feedback import feedback_routes
from service.api.http.callers import Callers
from service.api.http.contract import install_contract
from service.api.http.cut_requests import AnswerCutRequests
from service.api.http.header_limits import HeaderLimits
from service.api.http.http_middleware import HttpMiddleware
from service.api.http.metrics_middleware import MetricsMiddleware
from service.api.http.problems import install_problem_handlers
from service.api.http.request_id import RequestIdMiddleware
from service.api.monitoring import console_routes, drift_routes, health_routes
from service.api.predict import frame_routes, model_routes, predict_routes
from service.api.predict.frame_schemas import FrameRequest
from service.api.predict.predict_schemas import BatchJson, PredictJson, PredictParameters
from service.detector.manifest import load_manifest
from service.infra.logs import ensure_logging
from service.infra.metrics import worker_stopped
from service.infra.settings import Settings
from service.serving.container import ServiceState, build_state

DESCRIPTION = """\
Keypoint prediction sets with a finite-sample coverage guarantee.

For each keypoint of each object you send, the service returns a ball or an ellipse in
image pixels that contains the true keypoint with probability at least 1 - epsilon
(inductive conformal prediction, Yang & Pavone, "Conformal Semantic Keypoint Detection
with Statistical Guarantees"). Errors are RFC 9457 problem+json.

Every response carries an `X-Request-ID` header, and every problem body a `request_id`: the
caller's `X-Request-ID` (1 to 128 visible ASCII characters), or one the service made up. The
service's log lines about the request carry the same id.
"""

DOCS_PAGES = ("/docs", "/redoc")
# The pages' own origin only. ReDoc's side menu always shows Redocly's logo from
# cdn.redoc.ly (no option hides it); this keeps the browser from even trying to fetch it,
# so an air-gapped page makes no request that waits on a network it cannot reach.
# Inline scripts and styles: FastAPI's page bootstrap, Swagger UI's and ReDoc's styling;
# blob: workers: ReDoc's search index.
DOCS_CONTENT_SECURITY_POLICY = (
    "default-src 'self'; script-src 'self' 'unsafe-inline'; style-src 'self' 'unsafe-inline'; "
    "img-src 'self' data:; font-src 'self' data:; worker-src 'self' blob:"
)


def create_app(settings: Settings | None = None, state: ServiceState | None = None) -> FastAPI:
    """Build the app; the model and store are loaded at start-up (or ``state`` is used as is). Settings
    are read now, and logging configured (unless the process did), so that a server started as
    ``uvicorn service.serving.main:app`` logs its start-up in the service's format."""
    settings = state.settings if state is not None else settings or Settings()
    ensure_logging(settings)

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        owned = state is None
        app.state.service = state or build_state(settings)
        app.state.predict_parts = predict_parts(app.state.service)
        # What start-up made (the model, the store, the schemas: 100,000 objects) lives as long as
        # the process: out of the collector's sight, a full collection walks only what requests
        # made. Each had cost 100 to 170 ms beside a flood, the polite client's p99 (docs/operations.md).
        gc.collect()
        gc.freeze()
        try:
            yield
        finally:
            gc.unfreeze()  # an app started again in this process (tests) freezes what it makes
            if owned:
                app.state.service.close()
            worker_stopped()

    # Swagger UI and ReDoc served from the package, not a CDN: many deployments (factories,
    # labs, vehicles) have no internet access.
    app = FastAPIOffline(
        docs_url=DOCS_PAGES[0],
        redoc_url=DOCS_PAGES[1],
        title="Conformal keypoint service",
        version=__version__,
        description=DESCRIPTION,
        lifespan=lifespan,
        generate_unique_id_function=operation_id,
    )
    app.add_middleware(AnswerCutRequests)  # inside the metrics and the access line: they see its 503
    app.add_middleware(MetricsMiddleware)
    app.add_middleware(DocsPagesPolicy)
    app.add_middleware(HeaderLimits)  # outside the metrics: headers refused before anything reads them
    app.add_middleware(RequestIdMiddleware)  # outside the access line, which logs the id
    install_problem_handlers(app)
    routers = (predict_routes, frame_routes, model_routes, calibration_routes, health_routes, drift_routes)
    for routes in (*routers, audit_routes, console_routes, feedback_routes):
        app.include_router(routes.router)
    app.include_router(feedback_routes.admin_router)

    def served_objects() -> tuple[str, ...]:
        service = getattr(app.state, "service", None)  # started: its model; else the one it would load
        if service is None:
            return load_manifest(settings.model.directory).object_names
        return service.detector.manifest.object_names

    parsed_by_hand = (PredictJson, PredictParameters, BatchJson, FrameRequest)
    install_contract(app, parsed_bodies=parsed_by_hand, object_names=served_objects)
    return app


def predict_parts(state: ServiceState) -> PredictParts:
    """What the predict routes take from the service (``service.api.deps.Predicting``)."""
    predict = (state.predictor, state.admission, state.cpu_pool, state.settings.predict.max_request_bytes)
    return PredictParts(*predict, Callers(state.predict_callers), state.retention, state.adaptive)


def operation_id(route: APIRoute) -> str:
    """The route function's name: what generated clients call the operation (``upload_calibration``)."""
    return route.name


class DocsPagesPolicy(HttpMiddleware):
    """Sends ``DOCS_CONTENT_SECURITY_POLICY`` with the API pages (``DOCS_PAGES``), nothing else."""

    async def handle(self, scope: Scope, receive: Receive, send: Send) -> None:
        if scope.get("path", "").removeprefix(scope.get("root_path", "")) not in DOCS_PAGES:
            await self.app(scope, receive, send)
            return

        async def send_with_policy(message: Message) -> None:
            if message["type"] == "http.response.start":
                policy = (b"content-security-policy", DOCS_CONTENT_SECURITY_POLICY.encode())
                message["headers"] = [*message.get("headers", []), policy]
            await send(message)

        await self.app(scope, receive, send_with_policy)
