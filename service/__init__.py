"""Conformal keypoint service: keypoint prediction sets with a coverage guarantee."""

# The one source of the version: pyproject.toml reads it (dynamic); the OpenAPI document
# and GET /v1/model report it.
__version__ = "0.1.0"
