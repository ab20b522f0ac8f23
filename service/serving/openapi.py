"""The OpenAPI document, generated from the app without starting it."""

from __future__ import annotations

from service.serving.app import create_app


def openapi_document() -> dict:
    return create_app().openapi()
