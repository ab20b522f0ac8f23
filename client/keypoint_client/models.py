"""Bodies of the prediction API, as typed, immutable models (the service's JSON, field for field)."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any, Literal

from pydantic import Field, SerializerFunctionWrapHandler, field_validator, model_serializer

from keypoint_client.sets import Frozen, Point, PredictionSet

Nonconformity = Literal["peak", "var", "cov"]
Coverage = Literal["keypoint", "object"]
Stratify = Literal["none", "difficulty", "group", "difficulty+group"]
GroupFallback = Literal["refuse", "pooled"]
Box = tuple[float, float, float, float]
Vector3 = tuple[float, float, float]
Matrix3 = tuple[Vector3, Vector3, Vector3]


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
    coverage_upper_bound: float = Field(
        description="and at most this: 1 - epsilon + 1/(n+1) without delta, (n+1-t)/(n+1) with delta"
    )
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


def _plain(value: Any) -> Any:
    """A numpy array as nested lists (``tolist()``), anything else as it is."""
    return value.tolist() if hasattr(value, "tolist") else value


class PoseCheck(Frozen):
    """A pose to test for membership in an instance's pose set: p_camera = rotation p_model + translation."""

    instance: int = Field(description="index into the request's instances")
    rotation: Matrix3 = Field(description="3x3 rotation matrix, rows first")
    translation: Vector3 = Field(description="in the units of the manifest's keypoints_3d")

    @field_validator("rotation", "translation", mode="before")
    @classmethod
    def _arrays_as_lists(cls, value: Any) -> Any:
        return _plain(value)


class PoseRequest(Frozen):
    """Ask for each instance's pose set (PURSE, Yang & Pavone CVPR 2023); needs ``coverage="object"``.

    ``K``: the camera matrix [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] in the response's image pixels
    (pixel centres at +0.5: add 0.5 to an OpenCV cx, cy). ``samples``: keypoint draws for the
    sampled inner bound (0 to 500). ``outer_bound``: certified upper bounds from the convex
    relaxation (the server's ``pose`` extra). ``outer_programs``: conic programs the search over
    rotation cells may spend to tighten them (0 to 2000, about 1 ms each). ``outer_splits``: rounds
    of the older branch-and-bound (0 to 8, seconds per instance). ``check``: poses to test.
    """

    K: Matrix3
    samples: int = 100
    outer_bound: bool = True
    outer_splits: int = 0
    outer_programs: int = 150
    check: tuple[PoseCheck, ...] = ()

    @field_validator("K", mode="before")
    @classmethod
    def _array_as_lists(cls, value: Any) -> Any:
        return _plain(value)

    @classmethod
    def pinhole(cls, fx: float, fy: float, cx: float, cy: float, **options: Any) -> PoseRequest:
        """The request for the camera with these intrinsics (no skew); ``options`` as the fields."""
        return cls.model_validate({"K": ((fx, 0.0, cx), (0.0, fy, cy), (0.0, 0.0, 1.0)), **options})


class SampledBound(Frozen):
    """Largest errors to poses found in the pose set by sampling: the worst case is at least this."""

    kind: Literal["sampled"] = "sampled"
    rotation_deg: float
    translation: float
    poses_found: int
    poses_tried: int
    boundary_poses: int = 0


class OuterBound(Frozen):
    """Upper bounds from the convex relaxation; trust them only when ``certified``. The ratios to
    the inner bound say how much of each may be slack (1: none)."""

    certified: bool = Field(description="solved and its dual certificate verified")
    status: str
    rotation_deg: float | None = None
    translation: float | None = None
    rotation_over_inner: float | None = None
    translation_over_inner: float | None = None


class PoseCheckResult(Frozen):
    rotation: Matrix3
    translation: Vector3
    inside: bool = Field(description="in the pose set: every keypoint in front of the camera and in its set")
    violations: list[float | None] = Field(
        description="per keypoint sqrt((y-c)^T L (y-c)), <= 1 inside its set; None: behind the camera"
    )


class Pose(Frozen):
    """An instance's pose set: an estimate inside it and bounds on the error of any pose in it.
    With object coverage at epsilon, the true pose is in the set with probability >= 1 - epsilon."""

    empty: bool = Field(description="no pose consistent with the sets was found (they likely missed)")
    rotation: Matrix3 | None
    translation: Vector3 | None
    method: Literal["pnp", "pnp+refined-into-set", "sampled", "none"]
    largest_violation: float | None = Field(description="the estimate's largest normalised distance (<= 1)")
    inner_bound: SampledBound | None
    inner_bound_note: str | None = None
    outer_bound: OuterBound | None
    checks: list[PoseCheckResult] = Field(default_factory=list)


class Instance(Frozen):
    object: str
    bbox: Box
    keypoints: list[Keypoint]
    pose: Pose | None = Field(default=None, description="present when the request asked for pose")

    @model_serializer(mode="wrap")
    def _without_absent_pose(self, handler: SerializerFunctionWrapHandler) -> dict[str, Any]:
        """As the API: an answer without pose has no ``pose`` key."""
        data: dict[str, Any] = handler(self)
        if self.pose is None:
            data.pop("pose", None)
        return data


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


class AdaptiveLevel(Frozen):
    """Adaptive conformal inference on a stream: |miscoverage - epsilon| <= long_run_bound."""

    guarantee: str = "adaptive"
    epsilon: float
    alpha: float
    served_epsilon: float
    gamma: float
    steps: int
    miscoverage: float | None
    label_lag: int  # L: the most updates a label came after its set's level (widens the bound)
    long_run_bound: float | None


class PredictResult(Frozen):
    """The answer to one image: per instance, per keypoint, a set and its guarantee."""

    model: ModelRef
    calibration: CalibrationRef
    image: ImageInfo
    instances: list[Instance]
    prediction_id: str | None = Field(
        default=None,
        exclude_if=lambda value: value is None,  # answers not retained keep their shape
        description="retained for feedback (retain=True, or sampled by the server): send_feedback's id",
    )
    adaptive: AdaptiveLevel | None = Field(
        default=None,
        exclude_if=lambda value: value is None,
        description="adaptive=True: the ACI bound that applies to these sets",
    )


class ModelInfo(Frozen):
    """The served model; ``manifest`` is its manifest.json as the service reads it."""

    name: str
    hash: str
    manifest: dict[str, Any]
    service_version: str
    execution_providers: list[str] = []  # onnxruntime providers in use (servers before 0.1.0 omit it)

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
