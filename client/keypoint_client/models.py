"""Bodies of the prediction API, as typed, immutable models (the service's JSON, field for field)."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any, Literal

from pydantic import Field

from keypoint_client.sets import Frozen, Point, PredictionSet

Nonconformity = Literal["peak", "var", "cov"]
Coverage = Literal["keypoint", "object"]
Box = tuple[float, float, float, float]


class InstanceRequest(Frozen):
    """One object in the image: its name (from ``model()``) and its box [x, y, width, height] in pixels."""

    object: str
    bbox: Box
    group: str | None = None  # the caller's group (camera, site), for stratify="group"


# An instance as InstanceRequest, ("duck", [x, y, w, h]) or {"object": "duck", "bbox": [x, y, w, h]}.
InstanceLike = InstanceRequest | tuple[str, Sequence[float]] | Mapping[str, Any]


def instance_request(instance: InstanceLike) -> InstanceRequest:
    if isinstance(instance, InstanceRequest):
        return instance
    if isinstance(instance, tuple):
        name, bbox = instance
        return InstanceRequest.model_validate({"object": name, "bbox": bbox})
    return InstanceRequest.model_validate(instance)


class BetaLaw(Frozen):
    a: int
    b: int


class SignalRange(Frozen):
    signal: str
    low: float | None = Field(description="the bin holds signal >= low (None: no lower edge)")
    high: float | None = Field(description="and signal < high (None: no upper edge)")


class Stratum(Frozen):
    """The Mondrian stratum whose calibration scores alone gave a keypoint's threshold."""

    kind: Literal["pooled", "difficulty", "group", "difficulty+group"]
    group: str | None = None
    bin: int | None = None
    edges: tuple[SignalRange, ...] | None = None
    conditional: bool = Field(description="the guarantee holds conditionally on the stratum")
    fallback: str | None = Field(default=None, description="why the pooled threshold answered instead")


class Guarantee(Frozen):
    """What the calibration guarantees for a set (Theorem 1 of Yang & Pavone)."""

    scope: Coverage
    n: int = Field(description="calibration scores used")
    t: int = Field(description="rank of the threshold among them (0: unbounded)")
    epsilon: float
    coverage_lower_bound: float = Field(description="marginal coverage is at least this (1 - epsilon)")
    coverage_upper_bound: float = Field(description="and at most this (1 - epsilon + 1/(n+1))")
    conditional_coverage: BetaLaw = Field(description="coverage given the calibration set ~ Beta(a, b)")
    delta: float | None = Field(default=None, description="PAC: P(coverage < 1-epsilon) <= this")
    pac_failure_probability: float | None = Field(
        default=None, description="exact P(Beta(a, b) < 1 - epsilon) for the chosen t"
    )
    stratum: Stratum | None = Field(
        default=None,
        exclude_if=lambda stratum: stratum is None,  # responses without stratify keep their shape
        description="which stratum answered (with stratify)",
    )

    @property
    def bounded(self) -> bool:
        """Whether the set is finite (t > 0)."""
        return self.t > 0


class KeypointStatistics(Frozen):
    """Raw statistics of the normalized heatmap, in heatmap pixels."""

    peak_probability: float
    peak: Point
    mean: Point
    gamma: float
    covariance: tuple[Point, Point]


class Keypoint(Frozen):
    index: int
    name: str
    point: Point = Field(description="point estimate in image pixels (the set's centre)")
    set: PredictionSet
    guarantee: Guarantee
    statistics: KeypointStatistics | None = None


class Instance(Frozen):
    object: str
    bbox: Box
    keypoints: list[Keypoint]


class ModelRef(Frozen):
    name: str
    hash: str


class CalibrationRef(Frozen):
    version: int
    nonconformity: Nonconformity
    coverage: Coverage
    epsilon: float
    delta: float | None


class ImageInfo(Frozen):
    width: int
    height: int


class PredictResult(Frozen):
    """The answer to one image: per instance, per keypoint, a set and its guarantee."""

    model: ModelRef
    calibration: CalibrationRef
    image: ImageInfo
    instances: list[Instance]


class ModelInfo(Frozen):
    """The served model; ``manifest`` is its manifest.json as the service reads it."""

    name: str
    hash: str
    manifest: dict[str, Any]
    service_version: str

    @property
    def object_names(self) -> list[str]:
        return [str(entry["name"]) for entry in self.manifest["objects"]]

    @property
    def keypoint_names(self) -> list[str]:
        return [str(entry["name"]) for entry in self.manifest["keypoints"]]


class Readiness(Frozen):
    status: str
    model: str
    model_hash: str
    active_calibration: int
    store: str  # "ok", or "unreachable" while predictions go on from memory
    cache_age_seconds: float
    store_error: str | None
