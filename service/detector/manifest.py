"""The model manifest: everything the service needs to know about an ONNX heatmap detector.

A model is a directory holding ``model.onnx`` and ``manifest.json``. The manifest
describes the input tensor (name, size, colour order, pixel scaling), the crop rule,
the heatmap output, the keypoints and the objects they belong to, and how heatmaps
are turned into probability maps. Any heatmap model is servable by writing one.
"""

from __future__ import annotations

import json
from pathlib import Path
from typing import Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator, model_validator

MANIFEST_FILENAME = "manifest.json"
MODEL_FILENAME = "model.onnx"


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True)


class InputSpec(_Strict):
    """The network input: ``(x / scale - mean) / std`` per channel, NCHW layout."""

    name: str = Field(min_length=1, description="ONNX input tensor name")
    height: int = Field(gt=0, le=4096)
    width: int = Field(gt=0, le=4096)
    layout: Literal["NCHW"] = "NCHW"
    color: Literal["RGB", "BGR", "GRAY"] = "RGB"
    scale: float = Field(default=255.0, gt=0)
    mean: tuple[float, ...] = (0.0, 0.0, 0.0)
    std: tuple[float, ...] = (1.0, 1.0, 1.0)

    @property
    def channels(self) -> int:
        return 1 if self.color == "GRAY" else 3

    @model_validator(mode="after")
    def _channel_stats_match(self) -> InputSpec:
        for field in ("mean", "std"):
            values = getattr(self, field)
            if len(values) != self.channels:
                raise ValueError(
                    f"input.{field} has {len(values)} values but color {self.color} "
                    f"has {self.channels} channel(s)"
                )
        if any(s <= 0 for s in self.std):
            raise ValueError("input.std values must be > 0")
        return self


class CropSpec(_Strict):
    """Square crop centred on the box, side ``max(w, h) * (1 + padding)``."""

    padding: float = Field(default=0.25, ge=0.0, le=4.0)


class OutputSpec(_Strict):
    """The heatmap output: ``(N, K, height, width)``, one channel per keypoint."""

    name: str = Field(min_length=1, description="ONNX output tensor name")
    height: int = Field(gt=0, le=1024)
    width: int = Field(gt=0, le=1024)


class HeatmapSpec(_Strict):
    """How a raw heatmap becomes a probability map, and the top-K used by var and cov."""

    normalization: Literal["anchor", "softmax", "relu"] = "anchor"
    temperature: float = Field(default=1.0, gt=0)
    top_k: int = Field(default=100, gt=0)


class KeypointSpec(_Strict):
    index: int = Field(ge=0, description="output channel of this keypoint")
    name: str = Field(min_length=1)
    object: str = Field(min_length=1)


class ObjectSpec(_Strict):
    name: str = Field(min_length=1)
    keypoints: tuple[int, ...] = Field(min_length=1, description="output channels, in order")
    keypoints_3d: tuple[tuple[float, float, float], ...] | None = Field(
        default=None, description="model-frame 3D keypoints, same order as keypoints"
    )

    @model_validator(mode="after")
    def _same_length_3d(self) -> ObjectSpec:
        if self.keypoints_3d is not None and len(self.keypoints_3d) != len(self.keypoints):
            raise ValueError(
                f"object {self.name!r}: keypoints_3d has {len(self.keypoints_3d)} rows "
                f"but keypoints has {len(self.keypoints)}"
            )
        return self


class Manifest(_Strict):
    """A validated model manifest (see README, "Bring your own model")."""

    name: str = Field(min_length=1)
    input: InputSpec
    crop: CropSpec = CropSpec()
    output: OutputSpec
    heatmap: HeatmapSpec = HeatmapSpec()
    keypoints: tuple[KeypointSpec, ...] = Field(min_length=1)
    objects: tuple[ObjectSpec, ...] = Field(min_length=1)

    @field_validator("keypoints")
    @classmethod
    def _indices_are_channels(cls, keypoints: tuple[KeypointSpec, ...]):
        indices = sorted(k.index for k in keypoints)
        if indices != list(range(len(keypoints))):
            raise ValueError("keypoint indices must be exactly 0..K-1, each once")
        return tuple(sorted(keypoints, key=lambda k: k.index))

    @model_validator(mode="after")
    def _objects_match_keypoints(self) -> Manifest:
        names = [o.name for o in self.objects]
        if len(set(names)) != len(names):
            raise ValueError("object names must be unique")
        for obj in self.objects:
            for index in obj.keypoints:
                if index >= len(self.keypoints):
                    raise ValueError(f"object {obj.name!r} lists keypoint {index}, which does not exist")
                if self.keypoints[index].object != obj.name:
                    raise ValueError(
                        f"object {obj.name!r} lists keypoint {index}, but that keypoint "
                        f"belongs to {self.keypoints[index].object!r}"
                    )
        listed = {i for o in self.objects for i in o.keypoints}
        orphans = [k.index for k in self.keypoints if k.index not in listed]
        if orphans:
            raise ValueError(f"keypoints {orphans} are not listed by any object")
        return self

    @property
    def num_keypoints(self) -> int:
        return len(self.keypoints)

    @property
    def stride(self) -> tuple[float, float]:
        """Input pixels per heatmap pixel, (x, y)."""
        return (self.input.width / self.output.width, self.input.height / self.output.height)

    def object(self, name: str) -> ObjectSpec:
        for obj in self.objects:
            if obj.name == name:
                return obj
        raise KeyError(name)

    @property
    def object_names(self) -> tuple[str, ...]:
        return tuple(o.name for o in self.objects)


def load_manifest(model_dir: Path) -> Manifest:
    """Read and validate ``manifest.json`` in ``model_dir``."""
    path = Path(model_dir) / MANIFEST_FILENAME
    return Manifest.model_validate(json.loads(path.read_text(encoding="utf-8")))
