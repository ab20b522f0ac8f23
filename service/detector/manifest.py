"""The model manifest: everything the service needs to know about an ONNX heatmap detector
(docs/bring-your-own-model.md). Validation gathers every problem, as ``<field path>: <what to do>``,
in one ``ManifestError`` naming the file.
"""

from __future__ import annotations

import functools
import json
from collections.abc import Iterable
from pathlib import Path
from typing import Annotated, Any, Literal

from pydantic import BaseModel, ConfigDict, Field, ValidationError, field_validator, model_validator

from service.conformal.statistics import DEFAULT_TOP_K

MANIFEST_FILENAME = "manifest.json"
MODEL_FILENAME = "model.onnx"

SHA256_PATTERN = "^[0-9a-f]{64}$"
#: what answers call a model that is not a compressed copy of another
ORIGINAL = "original"

Problem = tuple[str, str]  # (field path, message)


class ManifestError(ValueError):
    """A manifest that cannot be used; ``str()`` is one ``<file>: <field>: <problem>`` line per problem."""

    def __init__(self, source: Path | str, problems: list[Problem]) -> None:
        self.source = str(source)
        self.problems = problems
        super().__init__("\n".join(f"{self.source}: {field}: {message}" for field, message in problems))


def _refuse(problems: list[Problem]) -> None:
    """Raise a validator's problems as one ValueError, a ``path: message`` line each (relative paths)."""
    if problems:
        raise ValueError("\n".join(f"{field}: {message}" for field, message in problems))


class _Strict(BaseModel):
    model_config = ConfigDict(extra="forbid", frozen=True, allow_inf_nan=False)


def _input_side(side: str) -> Any:
    return Field(
        gt=0, le=4096, description=f"input {side} in pixels; the square crop is resized to height x width"
    )


class InputSpec(_Strict):
    """The network input: ``(pixel / scale - mean) / std`` per channel, in ``color`` order, NCHW."""

    name: str = Field(min_length=1, description="name of the ONNX graph input that takes the image batch")
    height: int = _input_side("height")
    width: int = _input_side("width")
    layout: Literal["NCHW"] = Field(
        default="NCHW", description="tensor layout: batch, channels, height, width (the only one supported)"
    )
    color: Literal["RGB", "BGR", "GRAY"] = Field(
        default="RGB",
        description="channel order the network expects; GRAY is one channel (colour images are converted)",
    )
    scale: float = Field(
        default=255.0,
        gt=0,
        description="8-bit pixel values are divided by this first: 255 maps them to [0, 1], 1 keeps 0..255",
    )
    mean: tuple[float, ...] = Field(
        default=(0.0, 0.0, 0.0),
        description="subtracted per channel after dividing by scale, in color order (one value for GRAY)",
    )
    std: tuple[float, ...] = Field(
        default=(1.0, 1.0, 1.0),
        description="divides per channel after subtracting mean, in color order (one value for GRAY); > 0",
    )

    @property
    def channels(self) -> int:
        return 1 if self.color == "GRAY" else 3

    @model_validator(mode="after")
    def _channel_stats_match(self) -> InputSpec:
        problems = []
        for field in ("mean", "std"):
            values = getattr(self, field)
            if len(values) != self.channels:
                message = f"has {len(values)} value(s) but color {self.color} has {self.channels} channel(s)"
                problems.append((field, f"{message}; give one value per channel"))
        for i, value in enumerate(self.std):
            if value <= 0:
                problems.append((f"std[{i}]", f"is {value:g}; every std must be > 0"))
        _refuse(problems)
        return self


class CropSpec(_Strict):
    """Square crop centred on the box, side ``max(w, h) * (1 + padding)``, resized to the input size."""

    padding: float = Field(
        default=0.25,
        ge=0.0,
        le=4.0,
        description="context around the box: the square crop's side is max(w, h) * (1 + padding)",
    )


class OutputSpec(_Strict):
    """The heatmap output: ``(N, K, height, width)``, one channel per keypoint."""

    name: str = Field(min_length=1, description="name of the ONNX graph output holding the heatmaps")
    height: int = Field(gt=0, le=1024, description="heatmap height in pixels")
    width: int = Field(gt=0, le=1024, description="heatmap width in pixels")


class HeatmapSpec(_Strict):
    """How a raw heatmap becomes a probability map, and the top-K used by var and cov."""

    normalization: Literal["anchor", "softmax", "relu"] = Field(
        default="anchor",
        description=(
            "raw heatmap -> probability map: anchor (subtract the minimum, zero below the median, "
            "divide by the sum; the reference implementation's), softmax (exp(h / temperature) "
            "divided by its sum) or relu (clip at 0, divide by the sum)"
        ),
    )
    temperature: float = Field(
        default=1.0, gt=0, description="softmax temperature; only softmax uses it, so other modes need 1"
    )
    top_k: int = Field(
        default=DEFAULT_TOP_K,
        ge=1,
        description=(
            "how many of the most probable heatmap pixels make the var/cov mean and covariance; "
            "1..output.height*output.width; when omitted, 100 or the heatmap's pixel count if smaller"
        ),
    )

    @model_validator(mode="after")
    def _temperature_needs_softmax(self) -> HeatmapSpec:
        if self.temperature != 1.0 and self.normalization != "softmax":
            message = (
                f"is {self.temperature:g} but normalization {self.normalization!r} does not use a "
                "temperature (only softmax does); remove it or set heatmap.normalization to softmax"
            )
            _refuse([("temperature", message)])
        return self


class KeypointSpec(_Strict):
    """One output channel: which keypoint of which object it is."""

    index: int = Field(ge=0, description="output channel of this keypoint: 0..K-1, each exactly once")
    name: str = Field(
        min_length=1,
        description="unique in the manifest: responses and calibration reports name keypoints by it",
    )
    object: str = Field(min_length=1, description="name of the object (objects[].name) it belongs to")


class ObjectSpec(_Strict):
    """One object class: its keypoints' channels, in the order of its COCO keypoint annotations."""

    name: str = Field(
        min_length=1, description="unique object name; predict instances and COCO category names refer to it"
    )
    keypoints: tuple[Annotated[int, Field(ge=0)], ...] = Field(
        min_length=1,
        description="output channels of its keypoints, each once, in the order of its COCO keypoint triples",
    )
    keypoints_3d: tuple[tuple[float, float, float], ...] | None = Field(
        default=None,
        description="model-frame 3D keypoints (x, y, z), one per entry of keypoints; served by GET /v1/model",
    )

    @model_validator(mode="after")
    def _keypoint_lists_fit(self) -> ObjectSpec:
        problems = []
        if self.keypoints_3d is not None and len(self.keypoints_3d) != len(self.keypoints):
            message = f"has {len(self.keypoints_3d)} rows but keypoints has {len(self.keypoints)}"
            problems.append(
                ("keypoints_3d", f"{message}; give one (x, y, z) per keypoint, in the same order")
            )
        for position, channel in _repeats(self.keypoints):
            first = self.keypoints.index(channel)
            problems.append((f"keypoints[{position}]", f"channel {channel} is already keypoints[{first}]"))
        _refuse(problems)
        return self


class VariantSpec(_Strict):
    """A compressed copy of another model, written by ``keypoint-service optimize`` (docs/variants.md)."""

    name: Literal["int8", "float16"] = Field(
        description="int8: static quantization, for CPUs; float16: for GPU execution providers"
    )
    source_name: str = Field(min_length=1, description="name of the model it was made from")
    source_sha256: str = Field(pattern=SHA256_PATTERN, description="sha256 of that model's model.onnx")
    model_sha256: str = Field(
        pattern=SHA256_PATTERN,
        description="sha256 of this folder's model.onnx: another model.onnx is refused, so that the variant"
        " an answer names is the one that ran",
    )
    ranges: str = Field(default="", description="int8: the images whose crops set the activation ranges")


class Manifest(_Strict):
    """A validated model manifest (see docs/bring-your-own-model.md)."""

    name: str = Field(min_length=1, description="model name, reported with every prediction")
    input: InputSpec = Field(description="the network input and how a crop becomes it")
    crop: CropSpec = Field(default=CropSpec(), description="how much context around the box is cropped")
    output: OutputSpec = Field(description="the heatmap output")
    heatmap: HeatmapSpec = Field(
        default=HeatmapSpec(), description="how heatmaps become probability maps and set statistics"
    )
    keypoints: tuple[KeypointSpec, ...] = Field(min_length=1, description="one entry per output channel")
    objects: tuple[ObjectSpec, ...] = Field(
        min_length=1, description="the object classes; every keypoint belongs to exactly one"
    )
    variant: VariantSpec | None = Field(
        default=None,
        exclude_if=lambda variant: variant is None,
        description="present in a folder written by `keypoint-service optimize`: which compressed copy of"
        " which model this is",
    )

    @model_validator(mode="before")
    @classmethod
    def _default_top_k_fits_the_heatmap(cls, data: Any) -> Any:
        # An omitted top_k on a heatmap of fewer pixels becomes h*w: a small heatmap needs no heatmap
        # section, an explicit top_k > h*w stays refusable, and versions record the K used.
        if not isinstance(data, dict):
            return data
        heatmap, output = data.get("heatmap", {}), data.get("output")
        if isinstance(heatmap, HeatmapSpec):
            heatmap = heatmap.model_dump(exclude_unset=True)
        if isinstance(output, OutputSpec):
            output = output.model_dump()
        if not (isinstance(heatmap, dict) and isinstance(output, dict)) or "top_k" in heatmap:
            return data
        height, width = output.get("height"), output.get("width")
        if type(height) is not int or type(width) is not int or min(height, width) < 1:
            return data  # the field checks report it
        if height * width >= DEFAULT_TOP_K:
            return data
        return {**data, "heatmap": {**heatmap, "top_k": height * width}}

    @field_validator("keypoints")
    @classmethod
    def _indices_are_channels(cls, keypoints: tuple[KeypointSpec, ...]) -> tuple[KeypointSpec, ...]:
        count = len(keypoints)
        problems = []
        indices = [k.index for k in keypoints]
        for position, index in enumerate(indices):
            if index >= count:
                message = f"is {index}, but with {count} keypoints the indices are the output channels"
                problems.append((f"[{position}].index", f"{message} 0..{count - 1}"))
        for position, index in _repeats(indices):
            message = (
                f"{index} is also keypoints[{indices.index(index)}].index; each channel gets one keypoint"
            )
            problems.append((f"[{position}].index", message))
        names = [k.name for k in keypoints]
        for position, name in _repeats(names):
            first = names.index(name)
            message = (
                f"{name!r} is also the name of keypoints[{first}] (channels {indices[first]} and "
                f"{indices[position]}); keypoint names must be unique in the manifest, rename one"
            )
            problems.append((f"[{position}].name", message))
        _refuse(problems)
        return tuple(sorted(keypoints, key=lambda k: k.index))

    @model_validator(mode="after")
    def _sections_agree(self) -> Manifest:
        _refuse(self._object_problems() + self._heatmap_problems())
        return self

    def _object_problems(self) -> list[Problem]:
        names = [o.name for o in self.objects]
        also = "is also objects[{}].name; object names must be unique"
        duplicates = [
            (f"objects[{i}].name", f"{name!r} {also.format(names.index(name))}")
            for i, name in _repeats(names)
        ]
        if duplicates:  # which object owns a keypoint is ambiguous until these are fixed
            return duplicates
        problems = []
        for keypoint in self.keypoints:
            if keypoint.object not in names:
                message = f"{keypoint.object!r} (of keypoint {keypoint.name!r}) is not an object; objects are"
                problems.append((f"keypoints[{keypoint.index}].object", f"{message} {', '.join(names)}"))
        count = len(self.keypoints)
        for i, obj in enumerate(self.objects):
            for j, channel in enumerate(obj.keypoints):
                where = f"objects[{i}].keypoints[{j}]"
                if channel >= count:
                    problems.append((where, f"channel {channel} does not exist (indices are 0..{count - 1})"))
                elif (owner := self.keypoints[channel].object) != obj.name and owner in names:
                    message = (
                        f"keypoint {channel} ({self.keypoints[channel].name!r}) belongs to object {owner!r} "
                        f"(keypoints[{channel}].object); list it under {owner!r} or change its object"
                    )
                    problems.append((where, message))
        listed = {channel for obj in self.objects for channel in obj.keypoints}
        for keypoint in self.keypoints:
            if keypoint.index not in listed and keypoint.object in names:
                message = (
                    f"does not list keypoint {keypoint.index} ({keypoint.name!r}), which says it belongs "
                    f"to {keypoint.object!r}; add its channel"
                )
                problems.append((f"objects[{names.index(keypoint.object)}].keypoints", message))
        return problems

    def _heatmap_problems(self) -> list[Problem]:
        pixels = self.output.height * self.output.width
        if self.heatmap.top_k <= pixels:
            return []
        message = (
            f"is {self.heatmap.top_k} but a {self.output.height}x{self.output.width} heatmap "
            f"(output.height x output.width) has {pixels} pixels; use 1..{pixels}"
        )
        return [("heatmap.top_k", message)]

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
    def variant_name(self) -> str:
        return self.variant.name if self.variant is not None else ORIGINAL

    @property
    def object_names(self) -> tuple[str, ...]:
        return tuple(o.name for o in self.objects)

    def summary(self) -> str:
        """A few lines for people: input, crop, output, heatmap settings, objects and their keypoints."""
        spec, out, heatmap = self.input, self.output, self.heatmap
        stride_x, stride_y = self.stride
        lines = [
            f"name      {self.name}",
            f"input     {spec.name!r} (N, {spec.channels}, {spec.height}, {spec.width}) {spec.color}, "
            f"(pixel / {spec.scale:g} - mean) / std, mean {list(spec.mean)}, std {list(spec.std)}",
            f"crop      square, side max(w, h) * {1 + self.crop.padding:g}",
            f"output    {out.name!r} (N, {self.num_keypoints}, {out.height}, {out.width}), "
            f"stride {stride_x:g} x {stride_y:g} input pixels",
            f"heatmap   {heatmap.normalization}"
            + (f" (temperature {heatmap.temperature:g})" if heatmap.normalization == "softmax" else "")
            + f", top_k {heatmap.top_k}",
            f"objects   {len(self.objects)}, {self.num_keypoints} keypoints",
            f"variant   {self.variant_name}"
            + (f" of {self.variant.source_name} ({self.variant.source_sha256[:12]})" if self.variant else ""),
        ]
        for obj in self.objects:
            names = ", ".join(f"{c} {self.keypoints[c].name}" for c in obj.keypoints)
            lines.append(f"  {obj.name}{' (3D)' if obj.keypoints_3d else ''}: {names}")
        return "\n".join(lines)


def _repeats(values: Iterable[Any]) -> list[tuple[int, Any]]:
    """(position, value) of every value already seen earlier in ``values``."""
    values = list(values)
    return [(position, value) for position, value in enumerate(values) if value in values[:position]]


def validate_manifest(data: Any, source: Path | str) -> Manifest:
    """A Manifest from parsed JSON, or a ManifestError listing every problem found with its field path."""
    try:
        return Manifest.model_validate(data)
    except ValidationError as error:
        raise ManifestError(source, _problems(error)) from None


def load_manifest(model_dir: Path) -> Manifest:
    """Read and validate ``manifest.json`` in ``model_dir`` (FileNotFoundError if there is none)."""
    path = Path(model_dir) / MANIFEST_FILENAME
    raw = path.read_bytes()
    try:
        data = json.loads(raw)
    except UnicodeDecodeError:
        raise ManifestError(path, [("(file)", "is not UTF-8 text; save it as UTF-8 JSON")]) from None
    except json.JSONDecodeError as error:
        where = f"line {error.lineno} column {error.colno}"
        raise ManifestError(path, [(where, f"not valid JSON: {error.msg}")]) from None
    return validate_manifest(data, path)


def manifest_json_schema() -> dict:
    """The JSON Schema of manifest.json (committed as docs/manifest.schema.json)."""
    return {"$schema": "https://json-schema.org/draft/2020-12/schema", **Manifest.model_json_schema()}


def _problems(error: ValidationError) -> list[Problem]:
    items = error.errors(include_url=False)
    failed_inside = {item["loc"][:n] for item in items for n in range(len(item["loc"]))}
    problems = []
    for item in items:
        where = _path(item["loc"])
        if item["type"] == "too_short" and item["loc"] in failed_inside:
            continue  # pydantic counts only the valid items: the items' own errors say it all
        if item["type"] == "value_error":  # ours: "relative path: message" lines (see _refuse)
            for line in str(item["ctx"]["error"]).splitlines():
                relative, sep, message = line.partition(": ")
                problems.append((_join(where, relative), message) if sep else (where or "(manifest)", line))
        elif item["type"] == "extra_forbidden":
            message = "is not a manifest field; check its spelling and place (docs/bring-your-own-model.md)"
            problems.append((where, message))
        else:
            problems.append((where or "(manifest)", item["msg"]))
    return problems


def _path(loc: tuple[int | str, ...]) -> str:
    return functools.reduce(_join, (f"[{part}]" if isinstance(part, int) else str(part) for part in loc), "")


def _join(path: str, relative: str) -> str:
    if not path or not relative:
        return path or relative
    return path + relative if relative.startswith("[") else f"{path}.{relative}"
