"""The FastAPI application factory."""

from __future__ import annotations

from collections.abc import AsyncIterator
from contextlib import asynccontextmanager

from fastapi import FastAPI

from service import __version__
from service.api.metrics import MetricsMiddleware
from service.api.problems import install_problem_handlers
from service.api.routes import admin, health, model, predict, predict_batch
from service.api.schemas import PredictJson
from service.metrics import worker_stopped
from service.settings import Settings
from service.state import ServiceState, build_state

DESCRIPTION = """\
Keypoint prediction sets with a finite-sample coverage guarantee.

For each keypoint of each object you send, the service returns a ball or an ellipse in
image pixels that contains the true keypoint with probability at least 1 - epsilon
(inductive conformal prediction, Yang & Pavone, "Conformal Semantic Keypoint Detection
with Statistical Guarantees"). Errors are RFC 9457 problem+json.
"""


def create_app(settings: Settings | None = None, state: ServiceState | None = None) -> FastAPI:
    """Build the app; the model and store are loaded at start-up (or ``state`` is used as is)."""

    @asynccontextmanager
    async def lifespan(app: FastAPI) -> AsyncIterator[None]:
        owned = state is None
        app.state.service = state or build_state(settings or Settings())
        try:
            yield
        finally:
            if owned:
                app.state.service.close()
            worker_stopped()

    app = FastAPI(
        title="Conformal keypoint service",
        version=__version__,
        description=DESCRIPTION,
        lifespan=lifespan,
    )
    app.add_middleware(MetricsMiddleware)
    install_problem_handlers(app)
    for router in (predict.router, predict_batch.router, model.router, admin.router, health.router):
        app.include_router(router)
    _document_raw_bodies(app)
    return app


def _document_raw_bodies(app: FastAPI) -> None:
    """Add the schemas of bodies parsed by hand (predict's JSON form) to the OpenAPI components.

    FastAPI only collects models it validates itself, so ``#/components/schemas/PredictJson``
    (referenced by the predict route's ``openapi_extra``) would otherwise dangle.
    """
    generate = app.openapi

    def openapi() -> dict:
        if app.openapi_schema is None:
            document = generate()
            schema = PredictJson.model_json_schema(ref_template="#/components/schemas/{model}")
            components = document.setdefault("components", {}).setdefault("schemas", {})
            components.update(schema.pop("$defs", {}))
            components["PredictJson"] = schema
            app.openapi_schema = document
        return app.openapi_schema

    app.openapi = openapi  # type: ignore[method-assign]
