"""Request and response bodies of the HTTP API (pydantic v2)."""

from __future__ import annotations

import math
from typing import Annotated, Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator

Nonconformity = Literal["peak", "var", "cov"]
Coverage = Literal["keypoint", "object"]
Stratify = Literal["none", "difficulty", "group", "difficulty+group"]
Point = tuple[float, float]
MAX_VERSION = 2**31 - 1  # the calibration store keeps version numbers in 32-bit INTEGER columns


class _Body(BaseModel):
    model_config = ConfigDict(extra="forbid")


class InstanceIn(_Body):
    """One object in the image: its class and its box in image pixels."""

    object: str = Field(min_length=1, max_length=200, description="object name from GET /v1/model")
    bbox: tuple[float, float, float, float] = Field(description="[x, y, width, height] in image pixels")
    group: str | None = Field(
        default=None, min_length=1, max_length=64, pattern=r"^[ -~]+$",
        description="the caller's group of this instance (camera, site) for stratify=group: its"
        " calibration instances carried the same COCO \"group\"",
    )  # fmt: skip

    @field_validator("bbox")
    @classmethod
    def _finite_positive(cls, bbox: tuple[float, float, float, float]):
        if not all(math.isfinite(v) for v in bbox):
            raise ValueError("bbox values must be finite numbers")
        if bbox[2] <= 0 or bbox[3] <= 0:
            raise ValueError("bbox width and height must be > 0")
        return bbox


class PredictOptions(_Body):
    """What set to compute, with which guarantee."""

    epsilon: float = Field(default=0.1, gt=0, lt=1, description="miscoverage rate: sets cover with 1-epsilon")
    nonconformity: Nonconformity = Field(default="cov", description="peak and var give balls, cov ellipses")
    coverage: Coverage = Field(
        default="keypoint",
        description="keypoint: each keypoint covered with 1-epsilon; "
        "object: all of an object's keypoints at once",
    )
    delta: float | None = Field(
        default=None,
        gt=0,
        lt=1,
        description="if set, coverage >= 1-epsilon holds with probability 1-delta "
        "over the calibration set (PAC); sets get larger",
    )
    calibration_version: int | None = Field(
        default=None, ge=1, le=MAX_VERSION, description="default: the active version"
    )
    include_statistics: bool = Field(default=False, description="add raw heatmap statistics per keypoint")
    stratify: Stratify | list[Stratify] = Field(
        default="none",
        description="Mondrian strata: none (pooled threshold), difficulty (bins of a label-free heatmap"
        " signal), group (instances[i].group), difficulty+group; the version must have them. Each"
        " keypoint's guarantee then holds conditionally on its stratum (guarantee.stratum)",
    )
    group_fallback: Literal["refuse", "pooled"] = Field(
        default="refuse",
        description="where a keypoint has no bounded stratum (unknown or missing group, too few"
        " calibration scores for epsilon, strata the version lacks): refuse (422 naming the known"
        " groups) or use the pooled threshold (guarantee.stratum says so)",
    )


class PredictParameters(PredictOptions):
    """The JSON part of a multipart predict request."""

    instances: list[InstanceIn] = Field(min_length=1, description="objects to locate keypoints for")


class PredictJson(PredictParameters):
    """A predict request as JSON, with the image base64-encoded."""

    image_base64: str = Field(min_length=1, description="JPEG or PNG file, base64 (standard alphabet)")


class BallSet(BaseModel):
    type: Literal["ball"] = "ball"
    center: Point
    radius: float


class EllipseSet(BaseModel):
    type: Literal["ellipse"] = "ellipse"
    center: Point
    shape_matrix: tuple[Point, Point] = Field(description="L with (y-c)^T L (y-c) <= 1")
    semi_axes: Point = Field(description="(a, b), a <= b, in pixels")
    angle_deg: float = Field(description="direction of the major axis b, degrees from +x towards +y")


class UnboundedSet(BaseModel):
    type: Literal["unbounded"] = "unbounded"
    reason: str


PredictionSet = Annotated[BallSet | EllipseSet | UnboundedSet, Field(discriminator="type")]


class BetaLaw(BaseModel):
    a: int
    b: int


class SignalRange(BaseModel):
    signal: str = Field(description="heatmap feature: peak_probability, gamma or anisotropy")
    low: float | None = Field(description="the bin holds signal >= low (null: no lower edge)")
    high: float | None = Field(description="and signal < high (null: no upper edge)")


class Stratum(BaseModel):
    """The Mondrian stratum whose calibration scores alone gave this keypoint's threshold."""

    kind: Literal["pooled", "difficulty", "group", "difficulty+group"]
    group: str | None = Field(default=None, description="the caller group (kind group)")
    bin: int | None = Field(default=None, description="difficulty bin of this keypoint (kind difficulty)")
    edges: list[SignalRange] | None = Field(default=None, description="the bin's range of each signal")
    conditional: bool = Field(
        description="true: n, t and the bounds are the stratum's, and coverage >= 1 - epsilon holds"
        " conditionally on the stratum (Mondrian conformal); false: marginal over all keypoints"
    )
    fallback: str | None = Field(default=None, description="why the pooled threshold answered instead")


class Guarantee(BaseModel):
    """What the calibration actually guarantees for this set (Theorem 1 of the paper)."""

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
    stratum: Stratum | None = Field(default=None, description="which stratum answered (with stratify)")


class KeypointStatistics(BaseModel):
    """Raw statistics of the normalized heatmap, in heatmap pixels (scores are computed there)."""

    peak_probability: float = Field(description="p*, probability of the argmax pixel")
    peak: Point = Field(description="q*, centre of the argmax pixel")
    mean: Point = Field(description="q-bar, top-K weighted mean")
    gamma: float = Field(description="square root of the top-K weighted variance")
    covariance: tuple[Point, Point] = Field(description="top-K weighted covariance, before regularization")


class KeypointOut(BaseModel):
    index: int
    name: str
    point: Point = Field(description="point estimate in image pixels (the set's centre)")
    set: PredictionSet
    guarantee: Guarantee
    statistics: KeypointStatistics | None = None


class InstanceOut(BaseModel):
    object: str
    bbox: tuple[float, float, float, float]
    keypoints: list[KeypointOut]


class ModelRef(BaseModel):
    name: str
    hash: str


class CalibrationRef(BaseModel):
    version: int
    nonconformity: Nonconformity
    coverage: Coverage
    epsilon: float
    delta: float | None


class ImageInfo(BaseModel):
    width: int
    height: int


class PredictResponse(BaseModel):
    model: ModelRef
    calibration: CalibrationRef
    image: ImageInfo
    instances: list[InstanceOut]


class Problem(BaseModel):
    """An RFC 9457 problem: what went wrong and what to fix (``application/problem+json``)."""

    model_config = ConfigDict(extra="allow")

    type: str = "about:blank"
    title: str
    status: int
    detail: str = Field(description="what to fix")
    instance: str | None = Field(default=None, description="the request's path")
    errors: list[str] | None = Field(default=None, description="every problem found")


class BatchItem(BaseModel):
    """The answer for one image of a batch: a result, or the problem that image alone had."""

    status: int = Field(description="200, or the status this image would have had on POST /v1/predict")
    result: PredictResponse | None = Field(default=None, description="present when status is 200")
    problem: Problem | None = Field(default=None, description="present otherwise")


class BatchResponse(BaseModel):
    items: list[BatchItem] = Field(description="one per image, in the order image_0, image_1, ...")
