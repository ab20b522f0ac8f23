"""Request and response bodies of the HTTP API (pydantic v2)."""

from __future__ import annotations

from typing import Annotated, Any, Literal

import numpy as np
from pydantic import (
    BaseModel,
    ConfigDict,
    Field,
    StrictBool,
    StrictFloat,
    StrictInt,
    ValidationInfo,
    field_validator,
)

from service.api.http.problems import Problem
from service.detector.boxes import MIN_BOX_SIDE_PX
from service.pose.camera import camera_matrix_problems

Nonconformity = Literal["peak", "var", "cov"]
Coverage = Literal["keypoint", "object"]
Stratify = Literal["none", "difficulty", "group", "difficulty+group"]
Point = tuple[float, float]
MAX_BATCH_IMAGES = 16  # images per POST /v1/predict/batch
MAX_VERSION = 2**31 - 1  # the calibration store keeps version numbers in 32-bit INTEGER columns
_NAME: Any = {"min_length": 1, "max_length": 64, "pattern": r"^[ -~]+$"}  # a group or stream: printable ASCII


class StrictBody(BaseModel):
    model_config = ConfigDict(extra="forbid")


def _box_size(schema: dict) -> None:
    """The validator's rule (width and height at least MIN_BOX_SIDE_PX) said in the JSON Schema too."""
    for size in schema["prefixItems"][2:]:
        size["minimum"] = MIN_BOX_SIDE_PX


class InstanceIn(StrictBody):
    """One object in the image: its class and its box in image pixels."""

    object: str = Field(min_length=1, max_length=200, description="object name from GET /v1/model")
    bbox: tuple[StrictFloat, StrictFloat, StrictFloat, StrictFloat] = Field(
        description=f"[x, y, width, height] in image pixels, width and height at least {MIN_BOX_SIDE_PX:g}",
        json_schema_extra=_box_size,
    )
    group: str | None = Field(
        None,
        **_NAME,
        description="the caller's group of this instance (camera, site) for stratify=group: its"
        ' calibration instances carried the same COCO "group"',
    )

    @field_validator("object")
    @classmethod
    def _known_object(cls, name: str, info: ValidationInfo) -> str:
        """With the manifest as context, an unknown name is one more problem of the same answer."""
        manifest = (info.context or {}).get("manifest")
        if manifest is not None and name not in manifest.object_names:
            known = ", ".join(manifest.object_names)
            raise ValueError(f"{name!r} is not an object of model {manifest.name!r} (known: {known})")
        return name

    @field_validator("bbox")
    @classmethod
    def _finite_positive(cls, bbox: tuple[float, float, float, float]):
        if not np.isfinite(bbox).all():
            raise ValueError("bbox values must be finite numbers")
        if bbox[2] < MIN_BOX_SIDE_PX or bbox[3] < MIN_BOX_SIDE_PX:
            raise ValueError(f"bbox width and height must be at least {MIN_BOX_SIDE_PX:g} pixel")
        return bbox


Vector3 = tuple[float, float, float]
Matrix3 = tuple[Vector3, Vector3, Vector3]
ROTATION_TOLERANCE = 1e-6


class PoseCheckIn(StrictBody):
    """A pose to test for membership in PURSE: p_camera = rotation @ p_model + translation."""

    instance: StrictInt = Field(ge=0, description="index into instances")
    rotation: Matrix3 = Field(description="3x3 rotation matrix, rows first (R^T R = I, det 1)")
    translation: Vector3 = Field(description="in the units of the manifest's keypoints_3d")

    @field_validator("rotation")
    @classmethod
    def _a_rotation(cls, rotation: Matrix3) -> Matrix3:
        r = np.array(rotation)
        if not np.isfinite(r).all():
            raise ValueError("rotation entries must be finite numbers")
        if np.abs(r.T @ r - np.eye(3)).max() > ROTATION_TOLERANCE or np.linalg.det(r) <= 0:
            raise ValueError(f"is not a rotation matrix (R^T R = I within {ROTATION_TOLERANCE:g}, det +1)")
        return rotation

    @field_validator("translation")
    @classmethod
    def _finite(cls, translation: Vector3) -> Vector3:
        if not np.isfinite(translation).all():
            raise ValueError("translation entries must be finite numbers")
        return translation


class PoseRequest(StrictBody):
    """Ask for pose sets (PURSE, Yang & Pavone CVPR 2023): needs coverage 'object'."""

    K: list[list[float]] = Field(
        description="camera matrix [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] in the response's image pixels"
    )
    samples: StrictInt = Field(
        100, ge=0, le=500, description="keypoint draws for the sampled (inner) bound; 0: none"
    )
    outer_bound: StrictBool = Field(
        True, description="solve the convex relaxation for certified upper bounds (pose extra)"
    )
    outer_programs: StrictInt = Field(
        150,
        ge=0,
        le=2000,
        description="conic programs the search over rotation cells may spend to tighten the outer bound "
        "(about 1 ms each); 0: the whole-space relaxation only",
    )
    check: list[PoseCheckIn] = Field(
        default_factory=list, max_length=100, description="poses to test for membership in PURSE"
    )

    @field_validator("K")
    @classmethod
    def _pinhole(cls, matrix: list[list[float]]) -> list[list[float]]:
        if problems := camera_matrix_problems(matrix):
            raise ValueError("; ".join(problems))
        return matrix


class PredictOptions(StrictBody):
    """What set to compute, with which guarantee."""

    epsilon: float = Field(0.1, gt=0, lt=1, description="miscoverage rate: sets cover with 1-epsilon")
    nonconformity: Nonconformity = Field("cov", description="peak and var give balls, cov ellipses")
    coverage: Coverage = Field(
        "keypoint",
        description="keypoint: each keypoint covered with 1-epsilon; "
        "object: all of an object's keypoints at once",
    )
    delta: float | None = Field(
        None,
        gt=0,
        lt=1,
        description="if set, coverage >= 1-epsilon holds with probability 1-delta "
        "over the calibration set (PAC); sets get larger",
    )
    calibration_version: StrictInt | None = Field(
        None, ge=1, le=MAX_VERSION, description="default: the active version"
    )
    include_statistics: StrictBool = Field(False, description="add raw heatmap statistics per keypoint")
    stratify: Stratify | list[Stratify] = Field(
        "none",
        description="Mondrian strata: none (pooled threshold), difficulty (bins of a label-free heatmap"
        " signal), group (instances[i].group), difficulty+group; the version must have them. Each"
        " keypoint's guarantee then holds conditionally on its stratum (guarantee.stratum)",
    )
    group_fallback: Literal["refuse", "pooled"] = Field(
        "refuse",
        description="where a keypoint has no bounded stratum (unknown or missing group, too few"
        " calibration scores for epsilon, strata the version lacks): refuse (422 naming the known"
        " groups) or use the pooled threshold (guarantee.stratum says so)",
    )
    pose: PoseRequest | None = Field(None, description="also return each instance's pose set")
    retain: StrictBool = Field(
        False,
        description="keep this answer for feedback: it then carries a prediction_id to send the true points"
        " to (POST /v1/feedback/{prediction_id}); CKS_FEEDBACK_RETAIN_SHARE retains a share unasked",
    )
    stream: str | None = Field(
        None,
        **_NAME,
        description="the camera stream this image comes from: live coverage is reported per stream, and"
        " its frames are grouped into looks (one vote per look)",
    )
    adaptive: StrictBool = Field(
        False,
        description="adaptive sets for this stream (needs stream; no delta, no stratify): the threshold"
        " follows the stream's feedback (ACI, Gibbs & Candes 2021) and the answer's adaptive block states"
        " the long-run bound that then applies instead of the calibration's guarantee; it is retained",
    )

    @field_validator("epsilon", mode="before")
    @classmethod
    def _a_probability(cls, epsilon: object) -> object:
        if isinstance(epsilon, int | float) and not 0 < epsilon < 1:
            raise ValueError(
                f"{epsilon} is not a probability: epsilon is the probability that a set misses its"
                " keypoint, between 0 and 1 (exclusive): 0.1 gives 90 % sets"
            )
        return epsilon


class PredictParameters(PredictOptions):
    """The JSON part of a multipart predict request."""

    instances: list[InstanceIn] = Field(min_length=1, description="objects to locate keypoints for")


class PredictJson(PredictParameters):
    """A predict request as JSON, with the image base64-encoded."""

    image_base64: str = Field(min_length=1, description="JPEG or PNG file, base64 (standard alphabet)")


class BatchJson(StrictBody):
    """Several images, each as POST /v1/predict's JSON body; answered one item per image."""

    items: list[PredictJson] = Field(
        min_length=1,
        max_length=MAX_BATCH_IMAGES,
        description="at most 16 images, each with its instances and options;"
        " an item the schema refuses is answered in its own item (status 422), the others as usual",
    )


class _SetOut(BaseModel):
    """A prediction set, told apart by ``type``: always sent, so required in the document."""

    model_config = ConfigDict(json_schema_serialization_defaults_required=True)


class BallSet(_SetOut):
    type: Literal["ball"] = "ball"
    center: Point
    radius: float


class EllipseSet(_SetOut):
    type: Literal["ellipse"] = "ellipse"
    center: Point
    shape_matrix: tuple[Point, Point] = Field(description="L with (y-c)^T L (y-c) <= 1")
    semi_axes: Point = Field(description="(a, b), a <= b, in pixels")
    angle_deg: float = Field(description="direction of the major axis b, degrees from +x towards +y")


class UnboundedSet(_SetOut):
    type: Literal["unbounded"] = "unbounded"
    reason: str


PredictionSet = Annotated[
    BallSet | EllipseSet | UnboundedSet, Field(discriminator="type", title="KeypointSet")
]  # the title names the union for generators (openapi-generator made a model "Set" of "set")


class BetaLaw(BaseModel):
    a: int = Field(description="`n + 1 - t`")
    b: int = Field(description="`t`")


class SignalRange(BaseModel):
    signal: str = Field(description="heatmap feature: peak_probability, gamma or anisotropy")
    low: float | None = Field(description="the bin holds signal >= low (null: no lower edge)")
    high: float | None = Field(description="and signal < high (null: no upper edge)")


class Stratum(BaseModel):
    """The Mondrian stratum whose calibration scores alone gave this keypoint's threshold."""

    kind: Literal["pooled", "difficulty", "group", "difficulty+group"]
    group: str | None = Field(None, description="the caller group (kind group)")
    bin: int | None = Field(None, description="difficulty bin of this keypoint (kind difficulty)")
    edges: list[SignalRange] | None = Field(None, description="the bin's range of each signal")
    conditional: bool = Field(
        description="true: n, t and the bounds are the stratum's, and coverage >= 1 - epsilon holds"
        " conditionally on the stratum (Mondrian conformal); false: marginal over all keypoints"
    )
    fallback: str | None = Field(None, description="why the pooled threshold answered instead")


class Guarantee(BaseModel):
    """What the calibration actually guarantees for this set (Theorem 1 of the paper)."""

    scope: Coverage
    model_variant: str = Field(
        description="the model variant the calibration was scored with and the set computed by; a"
        " calibration is never served with another variant",
        examples=["original"],
    )
    n: int = Field(description="calibration scores used")
    t: int = Field(
        description="rank of the threshold among them (0: unbounded): `floor((n+1) * epsilon)` without delta,"
        " with delta the largest t up to that with pac_failure_probability <= delta"
    )
    epsilon: float
    coverage_lower_bound: float = Field(description="marginal coverage is at least this: `1 - epsilon`")
    coverage_upper_bound: float = Field(
        description="and at most this: `min(1, max(1 - epsilon + 1/(n+1), 1 - t/(n+1)))`; without delta"
        " 1 - epsilon + 1/(n+1) (Theorem 1), with delta the exact marginal coverage (n+1-t)/(n+1)"
        " (its t is smaller)"
    )
    conditional_coverage: BetaLaw = Field(description="coverage given the calibration set ~ Beta(a, b)")
    delta: float | None = Field(
        None,
        description="PAC: `pac_failure_probability <= delta`, i.e. P(coverage < 1-epsilon) <= this",
    )
    pac_failure_probability: float | None = Field(
        None, description="exact `P(Beta(a, b) < 1 - epsilon)` for the chosen t (null without delta)"
    )
    stratum: Stratum | None = Field(
        None,
        exclude_if=lambda stratum: stratum is None,  # responses without stratify keep their shape
        description="which Mondrian stratum answered: present when the request asked for stratify",
    )


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


class SampledBoundOut(BaseModel):
    """Largest errors to poses found in PURSE by sampling: the worst case is at least this."""

    kind: Literal["sampled"] = "sampled"
    rotation_deg: float
    translation: float
    poses_found: int
    poses_tried: int
    boundary_poses: int = Field(
        0, description="poses found by pushing the estimate to PURSE's boundary (not counted above)"
    )


class OuterBoundOut(BaseModel):
    """Upper bounds from the convex relaxation; trust them only when certified is true."""

    certified: bool = Field(description="solved and its dual certificate verified")
    status: str
    rotation_deg: float | None = None
    translation: float | None = None
    rotation_over_inner: float | None = Field(
        None,
        description="tightness: rotation_deg / the inner bound's (1: no slack; the worst case lies between)",
    )
    translation_over_inner: float | None = Field(
        None, description="tightness: translation / the inner bound's (1: no slack)"
    )


class PoseCheckOut(BaseModel):
    rotation: Matrix3
    translation: Vector3
    inside: bool = Field(description="in PURSE: every keypoint in front of the camera and in its set")
    violations: list[float | None] = Field(
        description="per keypoint sqrt((y-c)^T L (y-c)), <= 1 inside its set; null: behind the camera"
    )


class PoseOut(BaseModel):
    """The instance's pose set: an estimate inside PURSE and bounds on the error of any pose in it."""

    empty: bool = Field(description="no pose consistent with the sets was found (they likely missed)")
    rotation: Matrix3 | None
    translation: Vector3 | None
    method: Literal["pnp", "pnp+refined-into-set", "sampled", "none"]
    largest_violation: float | None = Field(description="the estimate's largest normalised distance (<= 1)")
    inner_bound: SampledBoundOut | None
    inner_bound_note: str | None = Field(
        None,
        description="why there is no inner bound, or that it is sampling's alone (the boundary search"
        " needs the pose extra's SciPy); absent: the samples and the boundary search made it",
    )
    outer_bound: OuterBoundOut | None
    checks: list[PoseCheckOut] = Field(default_factory=list)


class InstanceOut(BaseModel):
    object: str
    bbox: tuple[float, float, float, float]
    keypoints: list[KeypointOut]
    pose: PoseOut | None = Field(
        None,
        exclude_if=lambda pose: pose is None,  # responses without pose keep their shape
        description="present when the request asked for pose",
    )


class ModelRef(BaseModel):
    name: str
    hash: str
    variant: str = Field(
        description="which copy of the model ran and was calibrated: `original`, or the `int8` or `float16`"
        " variant `keypoint-service optimize` made (GET /v1/model names its source)",
        examples=["original"],
    )


class CalibrationRef(BaseModel):
    version: int
    nonconformity: Nonconformity
    coverage: Coverage
    epsilon: float
    delta: float | None


class ImageInfo(BaseModel):
    width: int
    height: int


class AdaptiveOut(BaseModel):
    """Adaptive conformal inference on this stream: what the sets were served at, and its bound."""

    guarantee: Literal["adaptive"] = "adaptive"
    epsilon: float = Field(description="the target miscoverage")
    alpha: float = Field(description="alpha_t after the stream's labels so far")
    served_epsilon: float = Field(description="the level these sets were computed at (alpha_t, clipped)")
    gamma: float = Field(description="ACI step size (0.005)")
    steps: int = Field(description="T: labels learned from")
    miscoverage: float | None = Field(description="share of the T labels the sets missed")
    label_lag: int = Field(
        description="L: the most updates a label has come after the level its set was served at"
        " (the other labels of its answer, and those that arrived while it was in flight)"
    )
    long_run_bound: float | None = Field(
        description="|miscoverage - epsilon| <= (max(epsilon, 1 - epsilon) + gamma (L + 1)) / (gamma T),"
        " any shift (docs/feedback.md)"
    )


class PredictResponse(BaseModel):
    model: ModelRef
    calibration: CalibrationRef
    image: ImageInfo
    instances: list[InstanceOut]
    prediction_id: str | None = Field(
        None,
        exclude_if=lambda value: value is None,  # answers not retained keep their shape
        description="present when the answer was retained for feedback: POST /v1/feedback/{prediction_id}",
    )
    adaptive: AdaptiveOut | None = Field(
        None,
        exclude_if=lambda value: value is None,
        description="present with adaptive sets: the guarantee that applies is this long-run bound",
    )


class BatchItem(BaseModel):
    """The answer for one image of a batch: a result, or the problem that image alone had."""

    status: int = Field(description="200, or the status this image would have had on POST /v1/predict")
    result: PredictResponse | None = Field(None, description="present when status is 200")
    problem: Problem | None = Field(None, description="present otherwise")


class BatchResponse(BaseModel):
    items: list[BatchItem] = Field(description="one per image, in the order image_0, image_1, ...")
