"""What model is served: manifest, keypoints, objects, hash, and the service's version."""

from __future__ import annotations

from fastapi import APIRouter
from pydantic import BaseModel, Field

from service import __version__
from service.api.deps import Model
from service.detector.manifest import Manifest

router = APIRouter(tags=["model"])


class ModelInfo(BaseModel):
    name: str
    hash: str
    variant: str = Field(
        description="`original`, or the `int8` or `float16` variant of `manifest.variant.source_name`",
        examples=["original"],
    )
    manifest: Manifest
    service_version: str = Field(description="the version of the service (`keypoint-service --version`)")
    execution_providers: list[str] = Field(
        description="the onnxruntime execution providers the model runs on, in order of preference"
        " (CKS_EXECUTION_PROVIDERS)",
        examples=[["CPUExecutionProvider"]],
    )


@router.get("/v1/model", response_model=ModelInfo, summary="The served model, its keypoints and objects")
async def model_info(detector: Model) -> ModelInfo:
    return ModelInfo(
        name=detector.manifest.name,
        hash=detector.model_hash,
        variant=detector.manifest.variant_name,
        manifest=detector.manifest,
        service_version=__version__,
        execution_providers=detector.execution_providers,
    )
