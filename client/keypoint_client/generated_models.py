# Generated from openapi/openapi.json by datamodel-code-generator 0.97.0: do not edit.
# Regenerate with: python client/generate_models.py
# ruff: noqa: E501

from __future__ import annotations

from typing import Annotated, Any, Literal

from pydantic import AwareDatetime, ConfigDict, Field
from typing_extensions import TypeAliasType

from keypoint_client.bases import (
    ActivationLogBase,
    Frozen,
    GuaranteeBase,
    JobBase,
    ModelInfoBase,
    PoseRequestBase,
    TakesArrays,
)
from keypoint_client.sets import BallGeometry, EllipseGeometry, UnboundedGeometry


class ActivationIn(Frozen):
    """force=true needs a non-blank reason (checked; JSON Schema says so with if/then)."""

    model_config = ConfigDict(
        extra="forbid",
    )
    force: bool = Field(False, title="Force")
    """activate although the guardrails refuse it (needs a reason; audited)"""
    reason: str = Field("", max_length=2000, title="Reason")
    """why; required (not blank) with force"""


class ActivationOut(Frozen):
    activated_at: AwareDatetime = Field(..., title="Activated At")
    reason: str = Field(..., title="Reason")
    seq: int = Field(..., title="Seq")
    version: int = Field(..., title="Version")
    who: str = Field(..., title="Who")


class AdaptiveOut(Frozen):
    """Adaptive conformal inference on this stream: what the sets were served at, and its bound."""

    alpha: float = Field(..., title="Alpha")
    """alpha_t after the stream's labels so far"""
    epsilon: float = Field(..., title="Epsilon")
    """the target miscoverage"""
    gamma: float = Field(..., title="Gamma")
    """ACI step size (0.005)"""
    guarantee: Literal["adaptive"] = Field("adaptive", title="Guarantee")
    label_lag: int = Field(..., title="Label Lag")
    """L: the most updates a label has come after the level its set was served at (the other labels of its answer, and those that arrived while it was in flight)"""
    long_run_bound: float | None = Field(..., title="Long Run Bound")
    """|miscoverage - epsilon| <= (max(epsilon, 1 - epsilon) + gamma (L + 1)) / (gamma T), any shift (docs/feedback.md)"""
    miscoverage: float | None = Field(..., title="Miscoverage")
    """share of the T labels the sets missed"""
    served_epsilon: float = Field(..., title="Served Epsilon")
    """the level these sets were computed at (alpha_t, clipped)"""
    steps: int = Field(..., title="Steps")
    """T: labels learned from"""


class AuditBatchOut(Frozen):
    annotations: int = Field(..., title="Annotations")
    """annotations in the batch"""
    duplicates_dropped: int = Field(..., title="Duplicates Dropped")
    name: str = Field(..., title="Name")
    note: str = Field(..., title="Note")
    rejected: int = Field(..., title="Rejected")
    """instances left out (box rule, strict decoding)"""
    rejections: list[str] = Field(..., title="Rejections")
    """the first of them, with why"""
    sha256: str = Field(..., title="Sha256")


class AuditEntryOut(Frozen):
    action: str = Field(..., title="Action")
    """upload, calibration, activation, rollback, retry"""
    at: AwareDatetime = Field(..., title="At")
    client: str = Field(..., title="Client")
    """the client's address"""
    details: dict[str, Any] = Field(..., title="Details")
    outcome: str = Field(..., title="Outcome")
    """e.g. accepted, refused, stored, failed, activated, forced"""
    previous_version: int | None = Field(..., title="Previous Version")
    reason: str = Field(..., title="Reason")
    seq: int = Field(..., title="Seq")
    version: int | None = Field(..., title="Version")
    who: str = Field(..., title="Who")
    """the operator (the admin token's name) or the CLI user"""


class AuditPage(Frozen):
    entries: list[AuditEntryOut] = Field(..., title="Entries")
    """newest first"""
    next_before: int | None = Field(..., title="Next Before")
    """pass as before= for the next (older) page; null at the end"""


class AuditSummaryOut(Frozen):
    batch_sha256: str = Field(..., title="Batch Sha256")
    created_at: AwareDatetime = Field(..., title="Created At")
    flagged: int = Field(..., title="Flagged")
    """figures flagged"""
    id: int = Field(..., title="Id")
    instances: int = Field(..., title="Instances")
    passed: bool = Field(..., title="Passed")
    version: int = Field(..., title="Version")
    """the calibration version audited"""
    who: str = Field(..., title="Who")


class BallSet(BallGeometry):
    center: tuple[float, float] = Field(..., title="Center")
    radius: float = Field(..., title="Radius")
    type: Literal["ball"] = Field(..., title="Type")


class BetaLaw(Frozen):
    a: int = Field(..., title="A")
    """`n + 1 - t`"""
    b: int = Field(..., title="B")
    """`t`"""


class CalibrationRef(Frozen):
    coverage: Literal["keypoint", "object"] = Field(..., title="Coverage")
    delta: float | None = Field(..., title="Delta")
    epsilon: float = Field(..., title="Epsilon")
    nonconformity: Literal["peak", "var", "cov"] = Field(..., title="Nonconformity")
    version: int = Field(..., title="Version")


class CoverageFigureOut(Frozen):
    """Empirical coverage against what Theorem 1 predicts for a valid calibration."""

    adjusted_p_value: float | None = Field(None, title="Adjusted P Value")
    """Holm-adjusted over the audit's tests"""
    band: list[float] | None = Field(..., title="Band")
    """the coverage a valid calibration gives this batch with 95% probability: the Beta-Binomial band for one keypoint (object in object scope); pooled, the calibration's spread with its units perfectly correlated plus the images' cluster-robust spread (docs/operations.md)"""
    coverage: float | None = Field(..., title="Coverage")
    """covered / m (null when m = 0)"""
    covered: int = Field(..., title="Covered")
    """of them, inside their sets"""
    expected: float | None = Field(None, title="Expected")
    """pooled: the mean coverage the calibration promises its units"""
    flagged: bool | None = Field(None, title="Flagged")
    """significantly low after Holm's correction"""
    in_band: bool = Field(..., title="In Band")
    m: int = Field(..., title="M")
    """audited instances (labeled keypoints, or fully labeled objects)"""
    n: int | None = Field(None, title="N")
    """calibration instances behind the threshold"""
    p_value: float = Field(..., title="P Value")
    """one-sided p-value of 'coverage below what the calibration promises' (pooled: normal approximation with the band's spread)"""
    promised: float | None = Field(..., title="Promised")
    """1 - epsilon, the coverage the version promises"""
    rank: int | None = Field(None, title="Rank")
    """l = floor((n+1) epsilon): Beta(n+1-l, l)"""


class CropSpec(Frozen):
    """Square crop centred on the box, side ``max(w, h) * (1 + padding)``, resized to the input size."""

    model_config = ConfigDict(
        extra="forbid",
    )
    padding: float = Field(0.25, ge=0.0, le=4.0, title="Padding")
    """context around the box: the square crop's side is max(w, h) * (1 + padding)"""


ShapeMatrixItem = TypeAliasType(
    "ShapeMatrixItem", Annotated[tuple[float, float], Field(..., max_length=2, min_length=2)]
)


class EllipseSet(EllipseGeometry):
    angle_deg: float = Field(..., title="Angle Deg")
    """direction of the major axis b, degrees from +x towards +y"""
    center: tuple[float, float] = Field(..., title="Center")
    semi_axes: tuple[float, float] = Field(..., title="Semi Axes")
    """(a, b), a <= b, in pixels"""
    shape_matrix: tuple[ShapeMatrixItem, ShapeMatrixItem] = Field(..., title="Shape Matrix")
    """L with (y-c)^T L (y-c) <= 1"""
    type: Literal["ellipse"] = Field(..., title="Type")


class FeatureTestOut(Frozen):
    alarm: bool = Field(..., title="Alarm")
    """ks: rejected by Holm at CKS_DRIFT_ALARM_LEVEL; psi: above the threshold"""
    live_n: int = Field(..., title="Live N")
    """live values in the window"""
    p_value: float | None = Field(..., title="P Value")
    """two-sided KS p-value (exact for small samples); null for psi"""
    reference_n: int = Field(..., title="Reference N")
    """calibration values of the reference version"""
    statistic: float | None = Field(..., title="Statistic")
    """KS distance D or PSI; null while a side has no values"""


AppendTo = TypeAliasType("AppendTo", Annotated[int, Field(..., ge=1, le=2147483647, title="Append To")])
"""new version = this one + the labels"""


ServedBy = TypeAliasType("ServedBy", Annotated[int, Field(..., ge=1, title="Served By")])
"""only labels of answers served by this version"""


Stream = TypeAliasType("Stream", Annotated[str, Field(..., max_length=64, title="Stream")])
"""only this camera stream's labels"""


class FieldCalibrationIn(Frozen):
    """Labelled feedback made a calibration version: which labels, and the upload's options."""

    model_config = ConfigDict(
        extra="forbid",
    )
    activate: bool = Field(False, title="Activate")
    allow_duplicate: bool = Field(False, title="Allow Duplicate")
    """store a version equal to a stored one (reason)"""
    append_to: AppendTo | None = Field(None, title="Append To")
    """new version = this one + the labels"""
    dedupe: bool = Field(False, title="Dedupe")
    """drop instances already counted instead of refusing"""
    force: bool = Field(False, title="Force")
    """activate past the guardrails (needs reason)"""
    name: str | None = Field(None, title="Name")
    """the source batch's name (default feedback-<sha256>)"""
    note: str = Field("", title="Note")
    reason: str = Field("", title="Reason")
    served_by: ServedBy | None = Field(None, title="Served By")
    """only labels of answers served by this version"""
    stream: Stream | None = Field(None, title="Stream")
    """only this camera stream's labels"""


class FieldCalibrationOut(Frozen):
    activated: bool = Field(..., title="Activated")
    summary: dict[str, Any] = Field(..., title="Summary")
    """as a calibration job's result: instances, added, rejections, problems"""
    version: int = Field(..., title="Version")


class FlaggedFigureOut(Frozen):
    adjusted_p_value: float | None = Field(None, title="Adjusted P Value")
    """Holm-adjusted over the audit's tests"""
    band: list[float] | None = Field(..., title="Band")
    """the coverage a valid calibration gives this batch with 95% probability: the Beta-Binomial band for one keypoint (object in object scope); pooled, the calibration's spread with its units perfectly correlated plus the images' cluster-robust spread (docs/operations.md)"""
    coverage: float | None = Field(..., title="Coverage")
    """covered / m (null when m = 0)"""
    covered: int = Field(..., title="Covered")
    """of them, inside their sets"""
    epsilon: float = Field(..., title="Epsilon")
    expected: float | None = Field(None, title="Expected")
    """pooled: the mean coverage the calibration promises its units"""
    flagged: bool | None = Field(None, title="Flagged")
    """significantly low after Holm's correction"""
    in_band: bool = Field(..., title="In Band")
    index: int | None = Field(None, title="Index")
    keypoint: str | None = Field(None, title="Keypoint")
    m: int = Field(..., title="M")
    """audited instances (labeled keypoints, or fully labeled objects)"""
    n: int | None = Field(None, title="N")
    """calibration instances behind the threshold"""
    nonconformity: Literal["peak", "var", "cov"] = Field(..., title="Nonconformity")
    object: str | None = Field(None, title="Object")
    """null: the section's overall figure"""
    p_value: float = Field(..., title="P Value")
    """one-sided p-value of 'coverage below what the calibration promises' (pooled: normal approximation with the band's spread)"""
    promised: float | None = Field(..., title="Promised")
    """1 - epsilon, the coverage the version promises"""
    rank: int | None = Field(None, title="Rank")
    """l = floor((n+1) epsilon): Beta(n+1-l, l)"""
    scope: str = Field(..., title="Scope")


class FrameIn(Frozen):
    """The camera frame the boxes and the answer's pixels refer to."""

    model_config = ConfigDict(
        extra="forbid",
    )
    encoding: Literal["rgb8", "bgr8", "mono8", "jpeg", "png"] | None = Field(None, title="Encoding")
    """with the whole frame as the one `pixels` part: its encoding (rgb8, bgr8, mono8: raw 8-bit pixels as ROS sensor_msgs/Image names them, row-major, no row padding (height * width * 3 or 1 bytes); jpeg, png: a file of exactly this size); left out when regions are sent"""
    height: int = Field(..., gt=0, le=2147483647, title="Height")
    """the full frame's height in pixels"""
    width: int = Field(..., gt=0, le=2147483647, title="Width")
    """the full frame's width in pixels"""


CalibrationVersion = TypeAliasType(
    "CalibrationVersion", Annotated[int, Field(..., ge=1, le=2147483647, title="Calibration Version")]
)
"""default: the active version"""


Delta = TypeAliasType("Delta", Annotated[float, Field(..., gt=0.0, lt=1.0, title="Delta")])
"""if set, coverage >= 1-epsilon holds with probability 1-delta over the calibration set (PAC); sets get larger"""


Stream1 = TypeAliasType(
    "Stream1", Annotated[str, Field(..., max_length=64, min_length=1, pattern="^[ -~]+$", title="Stream")]
)
"""the camera stream this image comes from: live coverage is reported per stream, and its frames are grouped into looks (one vote per look)"""


class GroupCoverageOut(Frozen):
    alarm: bool = Field(..., title="Alarm")
    """coverage proven below what the calibration gives: every rung of a ladder of floors over its Beta law (around floor) crossed (docs/feedback.md)"""
    coverage: str = Field(..., title="Coverage")
    """keypoint, or object (a unit is a fully labelled instance)"""
    covered: int = Field(..., title="Covered")
    """of them, inside the set served"""
    delta: float | None = Field(..., title="Delta")
    epsilon: float = Field(..., title="Epsilon")
    floor: float = Field(..., title="Floor")
    """the least coverage the version promises: the alarm_level/2 quantile of its Beta law (1 - epsilon with a PAC delta)"""
    guarantee: str = Field(..., title="Guarantee")
    """exchangeable (the calibration's), or adaptive (ACI sets: no floor and no alarm; their long-run bound is in each answer's adaptive block)"""
    labelled: int = Field(..., title="Labelled")
    """units labelled (keypoints, or instances with coverage object)"""
    level: str = Field(..., title="Level")
    """version (all keypoints), object, keypoint, stream, group (the caller's) or stratum (the Mondrian stratum that answered, with stratify)"""
    look_mean: float | None = Field(..., title="Look Mean")
    """mean vote (a look's share of covered units, all its frames)"""
    looks: int = Field(..., title="Looks")
    """independent looks that voted (frames of one scene are one look; a look votes once complete: when a label of its stream's next look is read)"""
    lower: float = Field(..., title="Lower")
    """anytime-valid lower confidence bound of the votes' mean"""
    name: str = Field(..., title="Name")
    nonconformity: str = Field(..., title="Nonconformity")
    promised: float = Field(..., title="Promised")
    """1 - epsilon"""
    upper: float = Field(..., title="Upper")
    """anytime-valid upper confidence bound"""
    version: int = Field(..., title="Version")


class Health(Frozen):
    status: str = Field(..., title="Status")


class HeatmapSpec(Frozen):
    """How a raw heatmap becomes a probability map, and the top-K used by var and cov."""

    model_config = ConfigDict(
        extra="forbid",
    )
    normalization: Literal["anchor", "softmax", "relu"] = Field("anchor", title="Normalization")
    """raw heatmap -> probability map: anchor (subtract the minimum, zero below the median, divide by the sum; the reference implementation's), softmax (exp(h / temperature) divided by its sum) or relu (clip at 0, divide by the sum)"""
    temperature: float = Field(1.0, gt=0.0, title="Temperature")
    """softmax temperature; only softmax uses it, so other modes need 1"""
    top_k: int = Field(100, ge=1, title="Top K")
    """how many of the most probable heatmap pixels make the var/cov mean and covariance; 1..output.height*output.width; when omitted, 100 or the heatmap's pixel count if smaller"""


class HistoryPointOut(Frozen):
    alarm: bool = Field(..., title="Alarm")
    alarms: int = Field(..., title="Alarms")
    """keypoint x feature alarms"""
    keypoint_statistics: list[float | None] = Field(..., title="Keypoint Statistics")
    """per channel: largest statistic over features"""
    object_statistics: dict[str, float | None] = Field(..., title="Object Statistics")
    recorded: int = Field(..., title="Recorded")
    """live values recorded so far"""
    time: float = Field(..., title="Time")
    """unix seconds"""
    version: int | None = Field(..., title="Version")


class ImageInfo(Frozen):
    height: int = Field(..., title="Height")
    width: int = Field(..., title="Width")


class InputSpec(Frozen):
    """The network input: ``(pixel / scale - mean) / std`` per channel, in ``color`` order, NCHW."""

    model_config = ConfigDict(
        extra="forbid",
    )
    color: Literal["RGB", "BGR", "GRAY"] = Field("RGB", title="Color")
    """channel order the network expects; GRAY is one channel (colour images are converted)"""
    height: int = Field(..., gt=0, le=4096, title="Height")
    """input height in pixels; the square crop is resized to height x width"""
    layout: Literal["NCHW"] = Field("NCHW", title="Layout")
    """tensor layout: batch, channels, height, width (the only one supported)"""
    mean: list[float] = Field([0.0, 0.0, 0.0], title="Mean")
    """subtracted per channel after dividing by scale, in color order (one value for GRAY)"""
    name: str = Field(..., min_length=1, title="Name")
    """name of the ONNX graph input that takes the image batch"""
    scale: float = Field(255.0, gt=0.0, title="Scale")
    """8-bit pixel values are divided by this first: 255 maps them to [0, 1], 1 keeps 0..255"""
    std: list[float] = Field([1.0, 1.0, 1.0], title="Std")
    """divides per channel after subtracting mean, in color order (one value for GRAY); > 0"""
    width: int = Field(..., gt=0, le=4096, title="Width")
    """input width in pixels; the square crop is resized to height x width"""


BboxItem = TypeAliasType("BboxItem", Annotated[float, Field(..., ge=1.0)])


Group = TypeAliasType(
    "Group", Annotated[str, Field(..., max_length=64, min_length=1, pattern="^[ -~]+$", title="Group")]
)
"""the caller's group of this instance (camera, site) for stratify=group: its calibration instances carried the same COCO "group\""""


class InstanceIn(Frozen):
    """One object in the image: its class and its box in image pixels."""

    model_config = ConfigDict(
        extra="forbid",
    )
    bbox: tuple[float, float, BboxItem, BboxItem] = Field(..., title="Bbox")
    """[x, y, width, height] in image pixels, width and height at least 1"""
    group: Group | None = Field(None, title="Group")
    """the caller's group of this instance (camera, site) for stratify=group: its calibration instances carried the same COCO "group\""""
    object: str = Field(..., title="Object")
    """object name from GET /v1/model"""


Keypoint = TypeAliasType(
    "Keypoint", Annotated[tuple[float, float, int], Field(..., max_length=3, min_length=3)]
)


class InstanceLabelsIn(Frozen):
    model_config = ConfigDict(
        extra="forbid",
    )
    instance: int = Field(..., ge=0, title="Instance")
    """index into the prediction's instances"""
    keypoints: list[Keypoint] = Field(..., title="Keypoints")
    """[x, y, v] per keypoint of the instance's object, in image pixels; v = 0 not labelled, 1 occluded, 2 visible (COCO); triples, not COCO's flat list x1, y1, v1, x2, ..."""


class JobOut(JobBase):
    created_at: AwareDatetime = Field(..., title="Created At")
    done: int = Field(..., title="Done")
    """instances scored so far"""
    errors: list[str] = Field(..., title="Errors")
    finished_at: AwareDatetime | None = Field(..., title="Finished At")
    id: str = Field(..., title="Id")
    kind: str = Field(..., title="Kind")
    result: dict[str, Any] = Field(..., title="Result")
    state: str = Field(..., title="State")
    """queued, running, succeeded, failed or interrupted (retryable)"""
    total: int = Field(..., title="Total")
    """instances to score"""
    version: int | None = Field(None, title="Version")
    """the calibration version the job produced"""


class JudgedKeypoint(Frozen):
    covered: bool = Field(..., title="Covered")
    """the true point lay in the set served"""
    index: int = Field(..., title="Index")
    """manifest keypoint index"""
    instance: int = Field(..., title="Instance")
    name: str = Field(..., title="Name")
    scores: dict[str, float] = Field(..., title="Scores")
    """its nonconformity score under each function"""


class KeypointChangeOut(Frozen):
    active_coverage_of_candidate: float | None = Field(..., title="Active Coverage Of Candidate")
    """share of the candidate's calibration scores inside the active version's sets"""
    keypoint: str = Field(..., title="Keypoint")
    n_after: int = Field(..., title="N After")
    """calibration scores of the candidate"""
    n_before: int | None = Field(..., title="N Before")
    """calibration scores of the active version (null: none active)"""
    object: str = Field(..., title="Object")
    set_area_ratio: float | None = Field(..., title="Set Area Ratio")
    """area of the candidate's sets over the active version's, for the same heatmap"""
    smallest_bounded_epsilon_after: float | None = Field(..., title="Smallest Bounded Epsilon After")
    smallest_bounded_epsilon_before: float | None = Field(..., title="Smallest Bounded Epsilon Before")
    """1/(n+1): below it, sets are unbounded"""


class KeypointCoverageOut(Frozen):
    adjusted_p_value: float | None = Field(None, title="Adjusted P Value")
    """Holm-adjusted over the audit's tests"""
    band: list[float] | None = Field(..., title="Band")
    """the coverage a valid calibration gives this batch with 95% probability: the Beta-Binomial band for one keypoint (object in object scope); pooled, the calibration's spread with its units perfectly correlated plus the images' cluster-robust spread (docs/operations.md)"""
    coverage: float | None = Field(..., title="Coverage")
    """covered / m (null when m = 0)"""
    covered: int = Field(..., title="Covered")
    """of them, inside their sets"""
    expected: float | None = Field(None, title="Expected")
    """pooled: the mean coverage the calibration promises its units"""
    flagged: bool | None = Field(None, title="Flagged")
    """significantly low after Holm's correction"""
    in_band: bool = Field(..., title="In Band")
    index: int = Field(..., title="Index")
    """the keypoint's output channel"""
    keypoint: str = Field(..., title="Keypoint")
    m: int = Field(..., title="M")
    """audited instances (labeled keypoints, or fully labeled objects)"""
    n: int | None = Field(None, title="N")
    """calibration instances behind the threshold"""
    object: str = Field(..., title="Object")
    p_value: float = Field(..., title="P Value")
    """one-sided p-value of 'coverage below what the calibration promises' (pooled: normal approximation with the band's spread)"""
    promised: float | None = Field(..., title="Promised")
    """1 - epsilon, the coverage the version promises"""
    rank: int | None = Field(None, title="Rank")
    """l = floor((n+1) epsilon): Beta(n+1-l, l)"""


class KeypointDriftOut(Frozen):
    features: dict[str, FeatureTestOut] = Field(..., title="Features")
    """peak_probability, gamma, anisotropy"""
    index: int = Field(..., title="Index")
    """manifest keypoint channel"""
    keypoint: str = Field(..., title="Keypoint")
    object: str = Field(..., title="Object")


class KeypointSpec(Frozen):
    """One output channel: which keypoint of which object it is."""

    model_config = ConfigDict(
        extra="forbid",
    )
    index: int = Field(..., ge=0, title="Index")
    """output channel of this keypoint: 0..K-1, each exactly once"""
    name: str = Field(..., min_length=1, title="Name")
    """unique in the manifest: responses and calibration reports name keypoints by it"""
    object: str = Field(..., min_length=1, title="Object")
    """name of the object (objects[].name) it belongs to"""


CovarianceItem = TypeAliasType(
    "CovarianceItem", Annotated[tuple[float, float], Field(..., max_length=2, min_length=2)]
)


class KeypointStatistics(Frozen):
    """Raw statistics of the normalized heatmap, in heatmap pixels (scores are computed there)."""

    covariance: tuple[CovarianceItem, CovarianceItem] = Field(..., title="Covariance")
    """top-K weighted covariance, before regularization"""
    gamma: float = Field(..., title="Gamma")
    """square root of the top-K weighted variance"""
    mean: tuple[float, float] = Field(..., title="Mean")
    """q-bar, top-K weighted mean"""
    peak: tuple[float, float] = Field(..., title="Peak")
    """q*, centre of the argmax pixel"""
    peak_probability: float = Field(..., title="Peak Probability")
    """p*, probability of the argmax pixel"""


class LiveCoverageOut(Frozen):
    alarm: bool = Field(..., title="Alarm")
    alarm_level: float = Field(..., title="Alarm Level")
    """CKS_FEEDBACK_ALARM_LEVEL: each group's probability of a false alarm, however long and often watched (the bounds form a confidence sequence at this level); exact for a group of one threshold, at most K times it for K thresholds whose coverages do not move together"""
    groups: list[GroupCoverageOut] = Field(..., title="Groups")


class ModelRef(Frozen):
    hash: str = Field(..., title="Hash")
    name: str = Field(..., title="Name")
    variant: str = Field(..., examples=["original"], title="Variant")
    """which copy of the model ran and was calibrated: `original`, or the `int8` or `float16` variant `keypoint-service optimize` made (GET /v1/model names its source)"""


class ObjectCoverageOut(Frozen):
    adjusted_p_value: float | None = Field(None, title="Adjusted P Value")
    """Holm-adjusted over the audit's tests"""
    band: list[float] | None = Field(..., title="Band")
    """the coverage a valid calibration gives this batch with 95% probability: the Beta-Binomial band for one keypoint (object in object scope); pooled, the calibration's spread with its units perfectly correlated plus the images' cluster-robust spread (docs/operations.md)"""
    coverage: float | None = Field(..., title="Coverage")
    """covered / m (null when m = 0)"""
    covered: int = Field(..., title="Covered")
    """of them, inside their sets"""
    expected: float | None = Field(None, title="Expected")
    """pooled: the mean coverage the calibration promises its units"""
    flagged: bool | None = Field(None, title="Flagged")
    """significantly low after Holm's correction"""
    in_band: bool = Field(..., title="In Band")
    m: int = Field(..., title="M")
    """audited instances (labeled keypoints, or fully labeled objects)"""
    n: int | None = Field(None, title="N")
    """calibration instances behind the threshold"""
    object: str = Field(..., title="Object")
    p_value: float = Field(..., title="P Value")
    """one-sided p-value of 'coverage below what the calibration promises' (pooled: normal approximation with the band's spread)"""
    promised: float | None = Field(..., title="Promised")
    """1 - epsilon, the coverage the version promises"""
    rank: int | None = Field(None, title="Rank")
    """l = floor((n+1) epsilon): Beta(n+1-l, l)"""


class ObjectDriftOut(Frozen):
    alarm: bool = Field(..., title="Alarm")
    features: dict[str, FeatureTestOut] = Field(..., title="Features")
    """largest statistic of its keypoints, their smallest p-value times their number (Bonferroni), alarm if any keypoint's is raised"""
    keypoints: list[int] = Field(..., title="Keypoints")
    """its keypoint channels"""
    object: str = Field(..., title="Object")


Keypoint1 = TypeAliasType("Keypoint1", Annotated[int, Field(..., ge=0)])


Keypoints3dItem = TypeAliasType(
    "Keypoints3dItem", Annotated[tuple[float, float, float], Field(..., max_length=3, min_length=3)]
)


class ObjectSpec(Frozen):
    """One object class: its keypoints' channels, in the order of its COCO keypoint annotations."""

    model_config = ConfigDict(
        extra="forbid",
    )
    keypoints: list[Keypoint1] = Field(..., min_length=1, title="Keypoints")
    """output channels of its keypoints, each once, in the order of its COCO keypoint triples"""
    keypoints_3d: list[Keypoints3dItem] | None = Field(None, title="Keypoints 3D")
    """model-frame 3D keypoints (x, y, z), one per entry of keypoints; served by GET /v1/model"""
    name: str = Field(..., min_length=1, title="Name")
    """unique object name; predict instances and COCO category names refer to it"""


class OuterBoundOut(Frozen):
    """Upper bounds from the convex relaxation; trust them only when certified is true."""

    certified: bool = Field(..., title="Certified")
    """solved and its dual certificate verified"""
    rotation_deg: float | None = Field(None, title="Rotation Deg")
    rotation_over_inner: float | None = Field(None, title="Rotation Over Inner")
    """tightness: rotation_deg / the inner bound's (1: no slack; the worst case lies between)"""
    status: str = Field(..., title="Status")
    translation: float | None = Field(None, title="Translation")
    translation_over_inner: float | None = Field(None, title="Translation Over Inner")
    """tightness: translation / the inner bound's (1: no slack)"""


class OutputSpec(Frozen):
    """The heatmap output: ``(N, K, height, width)``, one channel per keypoint."""

    model_config = ConfigDict(
        extra="forbid",
    )
    height: int = Field(..., gt=0, le=1024, title="Height")
    """heatmap height in pixels"""
    name: str = Field(..., min_length=1, title="Name")
    """name of the ONNX graph output holding the heatmaps"""
    width: int = Field(..., gt=0, le=1024, title="Width")
    """heatmap width in pixels"""


RotationItem = TypeAliasType(
    "RotationItem", Annotated[tuple[float, float, float], Field(..., max_length=3, min_length=3)]
)


class PoseCheckIn(TakesArrays):
    """A pose to test for membership in PURSE: p_camera = rotation @ p_model + translation."""

    model_config = ConfigDict(
        extra="forbid",
    )
    instance: int = Field(..., ge=0, title="Instance")
    """index into instances"""
    rotation: tuple[RotationItem, RotationItem, RotationItem] = Field(..., title="Rotation")
    """3x3 rotation matrix, rows first (R^T R = I, det 1)"""
    translation: tuple[float, float, float] = Field(..., title="Translation")
    """in the units of the manifest's keypoints_3d"""


class PoseCheckOut(Frozen):
    inside: bool = Field(..., title="Inside")
    """in PURSE: every keypoint in front of the camera and in its set"""
    rotation: tuple[RotationItem, RotationItem, RotationItem] = Field(..., title="Rotation")
    translation: tuple[float, float, float] = Field(..., title="Translation")
    violations: list[float | None] = Field(..., title="Violations")
    """per keypoint sqrt((y-c)^T L (y-c)), <= 1 inside its set; null: behind the camera"""


Rotation = TypeAliasType(
    "Rotation",
    Annotated[
        tuple[RotationItem, RotationItem, RotationItem],
        Field(..., max_length=3, min_length=3, title="Rotation"),
    ],
)


Translation = TypeAliasType(
    "Translation",
    Annotated[tuple[float, float, float], Field(..., max_length=3, min_length=3, title="Translation")],
)


class PoseRequest(PoseRequestBase):
    """Ask for pose sets (PURSE, Yang & Pavone CVPR 2023): needs coverage 'object'."""

    model_config = ConfigDict(
        extra="forbid",
    )
    K: list[list[float]] = Field(..., title="K")
    """camera matrix [[fx, 0, cx], [0, fy, cy], [0, 0, 1]] in the response's image pixels"""
    check: list[PoseCheckIn] | None = Field(None, max_length=100, title="Check")
    """poses to test for membership in PURSE"""
    outer_bound: bool = Field(True, title="Outer Bound")
    """solve the convex relaxation for certified upper bounds (pose extra)"""
    outer_programs: int = Field(150, ge=0, le=2000, title="Outer Programs")
    """conic programs the search over rotation cells may spend to tighten the outer bound (about 1 ms each); 0: the whole-space relaxation only"""
    samples: int = Field(100, ge=0, le=500, title="Samples")
    """keypoint draws for the sampled (inner) bound; 0: none"""


class PredictJson(Frozen):
    """A predict request as JSON, with the image base64-encoded."""

    model_config = ConfigDict(
        extra="forbid",
    )
    adaptive: bool = Field(False, title="Adaptive")
    """adaptive sets for this stream (needs stream; no delta, no stratify): the threshold follows the stream's feedback (ACI, Gibbs & Candes 2021) and the answer's adaptive block states the long-run bound that then applies instead of the calibration's guarantee; it is retained"""
    calibration_version: CalibrationVersion | None = Field(None, title="Calibration Version")
    """default: the active version"""
    coverage: Literal["keypoint", "object"] = Field("keypoint", title="Coverage")
    """keypoint: each keypoint covered with 1-epsilon; object: all of an object's keypoints at once"""
    delta: Delta | None = Field(None, title="Delta")
    """if set, coverage >= 1-epsilon holds with probability 1-delta over the calibration set (PAC); sets get larger"""
    epsilon: float = Field(0.1, gt=0.0, lt=1.0, title="Epsilon")
    """miscoverage rate: sets cover with 1-epsilon"""
    group_fallback: Literal["refuse", "pooled"] = Field("refuse", title="Group Fallback")
    """where a keypoint has no bounded stratum (unknown or missing group, too few calibration scores for epsilon, strata the version lacks): refuse (422 naming the known groups) or use the pooled threshold (guarantee.stratum says so)"""
    image_base64: str = Field(..., min_length=1, title="Image Base64")
    """JPEG or PNG file, base64 (standard alphabet)"""
    include_statistics: bool = Field(False, title="Include Statistics")
    """add raw heatmap statistics per keypoint"""
    instances: list[InstanceIn] = Field(..., min_length=1, title="Instances")
    """objects to locate keypoints for"""
    nonconformity: Literal["peak", "var", "cov"] = Field("cov", title="Nonconformity")
    """peak and var give balls, cov ellipses"""
    pose: PoseRequest | None = None
    """also return each instance's pose set"""
    retain: bool = Field(False, title="Retain")
    """keep this answer for feedback: it then carries a prediction_id to send the true points to (POST /v1/feedback/{prediction_id}); CKS_FEEDBACK_RETAIN_SHARE retains a share unasked"""
    stratify: (
        Literal["none", "difficulty", "group", "difficulty+group"]
        | list[Literal["none", "difficulty", "group", "difficulty+group"]]
    ) = Field("none", title="Stratify")
    """Mondrian strata: none (pooled threshold), difficulty (bins of a label-free heatmap signal), group (instances[i].group), difficulty+group; the version must have them. Each keypoint's guarantee then holds conditionally on its stratum (guarantee.stratum)"""
    stream: Stream1 | None = Field(None, title="Stream")
    """the camera stream this image comes from: live coverage is reported per stream, and its frames are grouped into looks (one vote per look)"""


class PredictParameters(Frozen):
    """The JSON part of a multipart predict request."""

    model_config = ConfigDict(
        extra="forbid",
    )
    adaptive: bool = Field(False, title="Adaptive")
    """adaptive sets for this stream (needs stream; no delta, no stratify): the threshold follows the stream's feedback (ACI, Gibbs & Candes 2021) and the answer's adaptive block states the long-run bound that then applies instead of the calibration's guarantee; it is retained"""
    calibration_version: CalibrationVersion | None = Field(None, title="Calibration Version")
    """default: the active version"""
    coverage: Literal["keypoint", "object"] = Field("keypoint", title="Coverage")
    """keypoint: each keypoint covered with 1-epsilon; object: all of an object's keypoints at once"""
    delta: Delta | None = Field(None, title="Delta")
    """if set, coverage >= 1-epsilon holds with probability 1-delta over the calibration set (PAC); sets get larger"""
    epsilon: float = Field(0.1, gt=0.0, lt=1.0, title="Epsilon")
    """miscoverage rate: sets cover with 1-epsilon"""
    group_fallback: Literal["refuse", "pooled"] = Field("refuse", title="Group Fallback")
    """where a keypoint has no bounded stratum (unknown or missing group, too few calibration scores for epsilon, strata the version lacks): refuse (422 naming the known groups) or use the pooled threshold (guarantee.stratum says so)"""
    include_statistics: bool = Field(False, title="Include Statistics")
    """add raw heatmap statistics per keypoint"""
    instances: list[InstanceIn] = Field(..., min_length=1, title="Instances")
    """objects to locate keypoints for"""
    nonconformity: Literal["peak", "var", "cov"] = Field("cov", title="Nonconformity")
    """peak and var give balls, cov ellipses"""
    pose: PoseRequest | None = None
    """also return each instance's pose set"""
    retain: bool = Field(False, title="Retain")
    """keep this answer for feedback: it then carries a prediction_id to send the true points to (POST /v1/feedback/{prediction_id}); CKS_FEEDBACK_RETAIN_SHARE retains a share unasked"""
    stratify: (
        Literal["none", "difficulty", "group", "difficulty+group"]
        | list[Literal["none", "difficulty", "group", "difficulty+group"]]
    ) = Field("none", title="Stratify")
    """Mondrian strata: none (pooled threshold), difficulty (bins of a label-free heatmap signal), group (instances[i].group), difficulty+group; the version must have them. Each keypoint's guarantee then holds conditionally on its stratum (guarantee.stratum)"""
    stream: Stream1 | None = Field(None, title="Stream")
    """the camera stream this image comes from: live coverage is reported per stream, and its frames are grouped into looks (one vote per look)"""


class Problem(Frozen):
    """
    An RFC 9457 problem: what went wrong and what to fix (``application/problem+json``).

    Some problems carry more members (``comparison`` on a refused activation, ``duplicates``
    on a refused upload); they are described where they are sent.
    """

    model_config = ConfigDict(
        extra="allow",
    )
    detail: str = Field(..., title="Detail")
    """what went wrong and what to fix"""
    errors: list[str] | None = Field(None, title="Errors")
    """every problem found, when there are several"""
    instance: str | None = Field(None, title="Instance")
    """the request's path"""
    request_id: str | None = Field(None, title="Request Id")
    """the request's X-Request-ID: quote it when reporting a problem"""
    status: int = Field(..., title="Status")
    """the HTTP status"""
    title: str = Field(..., title="Title")
    """the status in words"""
    type: str = Field("about:blank", title="Type")
    """always about:blank: the status says the kind"""


class Readiness(Frozen):
    active_calibration: int = Field(..., title="Active Calibration")
    cache_age_seconds: float = Field(..., title="Cache Age Seconds")
    """seconds since the store last confirmed the cached active calibration"""
    model: str = Field(..., title="Model")
    model_hash: str = Field(..., title="Model Hash")
    status: str = Field(..., title="Status")
    store: Literal["ok", "unreachable"] = Field(..., title="Store")
    """whether the calibration store answered the latest poll; predictions go on from memory while it is unreachable"""
    store_error: str | None = Field(..., title="Store Error")
    """why the store is unreachable (null while it answers)"""


class RegionIn(Frozen):
    """A rectangle of the frame (ROS sensor_msgs/RegionOfInterest), sent as one `pixels` part."""

    model_config = ConfigDict(
        extra="forbid",
    )
    encoding: Literal["rgb8", "bgr8", "mono8", "jpeg", "png"] = Field(..., title="Encoding")
    """rgb8, bgr8, mono8: raw 8-bit pixels as ROS sensor_msgs/Image names them, row-major, no row padding (height * width * 3 or 1 bytes); jpeg, png: a file of exactly this size"""
    height: int = Field(..., gt=0, le=2147483647, title="Height")
    """y_offset + height <= frame.height"""
    instances: list[int] = Field(..., min_length=1, title="Instances")
    """indexes into instances whose crops this region serves; each instance is served by exactly one region, which must hold its crop context (docs/predict.md)"""
    width: int = Field(..., gt=0, le=2147483647, title="Width")
    """x_offset + width <= frame.width"""
    x_offset: int = Field(..., ge=0, le=2147483647, title="X Offset")
    """its left column in the frame"""
    y_offset: int = Field(..., ge=0, le=2147483647, title="Y Offset")
    """its top row in the frame"""


class SampledBoundOut(Frozen):
    """Largest errors to poses found in PURSE by sampling: the worst case is at least this."""

    boundary_poses: int = Field(0, title="Boundary Poses")
    """poses found by pushing the estimate to PURSE's boundary (not counted above)"""
    kind: Literal["sampled"] = Field("sampled", title="Kind")
    poses_found: int = Field(..., title="Poses Found")
    poses_tried: int = Field(..., title="Poses Tried")
    rotation_deg: float = Field(..., title="Rotation Deg")
    translation: float = Field(..., title="Translation")


class SignalRange(Frozen):
    high: float | None = Field(..., title="High")
    """and signal < high (null: no upper edge)"""
    low: float | None = Field(..., title="Low")
    """the bin holds signal >= low (null: no lower edge)"""
    signal: str = Field(..., title="Signal")
    """heatmap feature: peak_probability, gamma or anisotropy"""


class SizeSummaryOut(Frozen):
    histogram_counts: list[int] = Field(..., title="Histogram Counts")
    histogram_edges: list[float] = Field(..., title="Histogram Edges")
    quantiles: dict[str, float] = Field(..., title="Quantiles")
    """p05, p25, p50, p75, p95"""


class SourceBatchOut(Frozen):
    instances: int = Field(..., title="Instances")
    name: str = Field(..., title="Name")
    sha256: str = Field(..., title="Sha256")


class StoreInfo(Frozen):
    active_version: int | None = Field(..., title="Active Version")
    data_dir: str = Field(..., title="Data Dir")
    """absolute data directory (uploads, kept job uploads, metrics)"""
    kind: str = Field(..., title="Kind")
    """sqlite or postgresql"""
    location: str = Field(..., title="Location")
    """the database file, or the PostgreSQL URL without password"""
    model_hash: str = Field(..., title="Model Hash")


class Stratum(Frozen):
    """The Mondrian stratum whose calibration scores alone gave this keypoint's threshold."""

    bin: int | None = Field(None, title="Bin")
    """difficulty bin of this keypoint (kind difficulty)"""
    conditional: bool = Field(..., title="Conditional")
    """true: n, t and the bounds are the stratum's, and coverage >= 1 - epsilon holds conditionally on the stratum (Mondrian conformal); false: marginal over all keypoints"""
    edges: list[SignalRange] | None = Field(None, title="Edges")
    """the bin's range of each signal"""
    fallback: str | None = Field(None, title="Fallback")
    """why the pooled threshold answered instead"""
    group: str | None = Field(None, title="Group")
    """the caller group (kind group)"""
    kind: Literal["pooled", "difficulty", "group", "difficulty+group"] = Field(..., title="Kind")


class ThresholdRow(Frozen):
    """Thresholds of one function at one epsilon; null means the set is unbounded."""

    epsilon: float = Field(..., title="Epsilon")
    keypoint: dict[str, float | None] = Field(..., title="Keypoint")
    """keypoint name -> threshold (keypoint scope)"""
    nonconformity: Literal["peak", "var", "cov"] = Field(..., title="Nonconformity")
    object: dict[str, float | None] = Field(..., title="Object")
    """object name -> threshold (object scope)"""


class UnboundedSet(UnboundedGeometry):
    reason: str = Field(..., title="Reason")
    type: Literal["unbounded"] = Field(..., title="Type")


class VariantSpec(Frozen):
    """A compressed copy of another model, written by ``keypoint-service optimize`` (docs/variants.md)."""

    model_config = ConfigDict(
        extra="forbid",
    )
    model_sha256: str = Field(..., pattern="^[0-9a-f]{64}$", title="Model Sha256")
    """sha256 of this folder's model.onnx: another model.onnx is refused, so that the variant an answer names is the one that ran"""
    name: Literal["int8", "float16"] = Field(..., title="Name")
    """int8: static quantization, for CPUs; float16: for GPU execution providers"""
    ranges: str = Field("", title="Ranges")
    """int8: the images whose crops set the activation ranges"""
    source_name: str = Field(..., min_length=1, title="Source Name")
    """name of the model it was made from"""
    source_sha256: str = Field(..., pattern="^[0-9a-f]{64}$", title="Source Sha256")
    """sha256 of that model's model.onnx"""


class VersionDetail(Frozen):
    active: bool = Field(..., title="Active")
    author: str = Field(..., title="Author")
    complete_per_object: dict[str, int] = Field(..., title="Complete Per Object")
    """fully labeled instances (object scope n)"""
    created_at: AwareDatetime = Field(..., title="Created At")
    instances: int = Field(..., title="Instances")
    labeled_per_keypoint: dict[str, int] = Field(..., title="Labeled Per Keypoint")
    """calibration scores per keypoint (n)"""
    normalization: dict[str, Any] = Field(..., title="Normalization")
    """the manifest settings the scores were computed under"""
    note: str = Field(..., title="Note")
    objects: dict[str, int] = Field(..., title="Objects")
    """instances per object"""
    parent_version: int | None = Field(..., title="Parent Version")
    source_batches: list[SourceBatchOut] = Field(..., title="Source Batches")
    strata: dict[str, Any] | None = Field(None, title="Strata")
    """Mondrian strata stored with the version (null: none): spec (difficulty signals, bins, min_instances; group), groups (labels known), bins per keypoint channel and group ('*' = all instances): edges of each signal and the calibration instances (counts) per bin"""
    thresholds: list[ThresholdRow] = Field(..., title="Thresholds")
    unusable_reason: str | None = Field(None, title="Unusable Reason")
    """why not, and what to do"""
    usable: bool = Field(..., title="Usable")
    """whether the current manifest can serve this version"""
    version: int = Field(..., title="Version")


class VersionSummary(Frozen):
    active: bool = Field(..., title="Active")
    author: str = Field(..., title="Author")
    created_at: AwareDatetime = Field(..., title="Created At")
    instances: int = Field(..., title="Instances")
    note: str = Field(..., title="Note")
    objects: dict[str, int] = Field(..., title="Objects")
    """instances per object"""
    parent_version: int | None = Field(..., title="Parent Version")
    source_batches: list[SourceBatchOut] = Field(..., title="Source Batches")
    version: int = Field(..., title="Version")


class ActivationLog(ActivationLogBase):
    activations: list[ActivationOut] = Field(..., title="Activations")
    active_version: int | None = Field(..., title="Active Version")


class AuditList(Frozen):
    audits: list[AuditSummaryOut] = Field(..., title="Audits")
    """newest first"""
    model_hash: str = Field(..., title="Model Hash")
    next_before: int | None = Field(..., title="Next Before")
    """pass as before= for the next (older) page; null at the end"""


class BatchJson(Frozen):
    """Several images, each as POST /v1/predict's JSON body; answered one item per image."""

    model_config = ConfigDict(
        extra="forbid",
    )
    items: list[PredictJson] = Field(..., max_length=16, min_length=1, title="Items")
    """at most 16 images, each with its instances and options; an item the schema refuses is answered in its own item (status 422), the others as usual"""


class ComparisonOut(Frozen):
    """A candidate version against the active one, and whether the guardrails allow activating it."""

    against: int | None = Field(..., title="Against")
    """the version compared with (null: nothing is active)"""
    allowed: bool = Field(..., title="Allowed")
    candidate: int | None = Field(..., title="Candidate")
    epsilon: float = Field(..., title="Epsilon")
    keypoints: list[KeypointChangeOut] = Field(..., title="Keypoints")
    median_set_area_ratio: float | None = Field(..., title="Median Set Area Ratio")
    min_instances: int = Field(..., title="Min Instances")
    """the floor of n per keypoint (CKS_MIN_CALIBRATION_INSTANCES)"""
    nonconformity: Literal["peak", "var", "cov"] = Field(..., title="Nonconformity")
    problems: list[str] = Field(..., title="Problems")
    """why activating would be refused (empty: allowed)"""


class CoverageSectionOut(Frozen):
    epsilon: float = Field(..., title="Epsilon")
    keypoints: list[KeypointCoverageOut] = Field(..., title="Keypoints")
    """keypoint scope only"""
    nonconformity: Literal["peak", "var", "cov"] = Field(..., title="Nonconformity")
    objects: list[ObjectCoverageOut] = Field(..., title="Objects")
    overall: CoverageFigureOut
    scope: str = Field(..., title="Scope")
    """keypoint or object"""


class FeedbackIn(Frozen):
    """The true points of some or all of a retained prediction's instances."""

    model_config = ConfigDict(
        extra="forbid",
    )
    instances: list[InstanceLabelsIn] = Field(..., max_length=1000, min_length=1, title="Instances")


class FeedbackOut(Frozen):
    calibration_version: int = Field(..., title="Calibration Version")
    covered: int = Field(..., title="Covered")
    """of them, inside the set served"""
    keypoints: list[JudgedKeypoint] = Field(..., title="Keypoints")
    labelled: int = Field(..., title="Labelled")
    """keypoints labelled"""
    prediction_id: str = Field(..., title="Prediction Id")


Regions = TypeAliasType("Regions", Annotated[list[RegionIn], Field(..., min_length=1, title="Regions")])
"""the frame's regions, each sent as a `pixels` part in this order; left out when the whole frame is the one `pixels` part (frame.encoding)"""


class FrameRequest(Frozen):
    """The JSON part `request` of POST /v1/predict/frame."""

    model_config = ConfigDict(
        extra="forbid",
    )
    adaptive: bool = Field(False, title="Adaptive")
    """adaptive sets for this stream (needs stream; no delta, no stratify): the threshold follows the stream's feedback (ACI, Gibbs & Candes 2021) and the answer's adaptive block states the long-run bound that then applies instead of the calibration's guarantee; it is retained"""
    calibration_version: CalibrationVersion | None = Field(None, title="Calibration Version")
    """default: the active version"""
    coverage: Literal["keypoint", "object"] = Field("keypoint", title="Coverage")
    """keypoint: each keypoint covered with 1-epsilon; object: all of an object's keypoints at once"""
    delta: Delta | None = Field(None, title="Delta")
    """if set, coverage >= 1-epsilon holds with probability 1-delta over the calibration set (PAC); sets get larger"""
    epsilon: float = Field(0.1, gt=0.0, lt=1.0, title="Epsilon")
    """miscoverage rate: sets cover with 1-epsilon"""
    frame: FrameIn
    group_fallback: Literal["refuse", "pooled"] = Field("refuse", title="Group Fallback")
    """where a keypoint has no bounded stratum (unknown or missing group, too few calibration scores for epsilon, strata the version lacks): refuse (422 naming the known groups) or use the pooled threshold (guarantee.stratum says so)"""
    include_statistics: bool = Field(False, title="Include Statistics")
    """add raw heatmap statistics per keypoint"""
    instances: list[InstanceIn] = Field(..., min_length=1, title="Instances")
    """objects to locate keypoints for"""
    nonconformity: Literal["peak", "var", "cov"] = Field("cov", title="Nonconformity")
    """peak and var give balls, cov ellipses"""
    pose: PoseRequest | None = None
    """also return each instance's pose set"""
    regions: Regions | None = Field(None, title="Regions")
    """the frame's regions, each sent as a `pixels` part in this order; left out when the whole frame is the one `pixels` part (frame.encoding)"""
    retain: bool = Field(False, title="Retain")
    """keep this answer for feedback: it then carries a prediction_id to send the true points to (POST /v1/feedback/{prediction_id}); CKS_FEEDBACK_RETAIN_SHARE retains a share unasked"""
    stratify: (
        Literal["none", "difficulty", "group", "difficulty+group"]
        | list[Literal["none", "difficulty", "group", "difficulty+group"]]
    ) = Field("none", title="Stratify")
    """Mondrian strata: none (pooled threshold), difficulty (bins of a label-free heatmap signal), group (instances[i].group), difficulty+group; the version must have them. Each keypoint's guarantee then holds conditionally on its stratum (guarantee.stratum)"""
    stream: Stream1 | None = Field(None, title="Stream")
    """the camera stream this image comes from: live coverage is reported per stream, and its frames are grouped into looks (one vote per look)"""


class Guarantee(GuaranteeBase):
    """What the calibration actually guarantees for this set (Theorem 1 of the paper)."""

    conditional_coverage: BetaLaw
    """coverage given the calibration set ~ Beta(a, b)"""
    coverage_lower_bound: float = Field(..., title="Coverage Lower Bound")
    """marginal coverage is at least this: `1 - epsilon`"""
    coverage_upper_bound: float = Field(..., title="Coverage Upper Bound")
    """and at most this: `min(1, max(1 - epsilon + 1/(n+1), 1 - t/(n+1)))`; without delta 1 - epsilon + 1/(n+1) (Theorem 1), with delta the exact marginal coverage (n+1-t)/(n+1) (its t is smaller)"""
    delta: float | None = Field(None, title="Delta")
    """PAC: `pac_failure_probability <= delta`, i.e. P(coverage < 1-epsilon) <= this"""
    epsilon: float = Field(..., title="Epsilon")
    model_variant: str = Field(..., examples=["original"], title="Model Variant")
    """the model variant the calibration was scored with and the set computed by; a calibration is never served with another variant"""
    n: int = Field(..., title="N")
    """calibration scores used"""
    pac_failure_probability: float | None = Field(None, title="Pac Failure Probability")
    """exact `P(Beta(a, b) < 1 - epsilon)` for the chosen t (null without delta)"""
    scope: Literal["keypoint", "object"] = Field(..., title="Scope")
    stratum: Stratum | None = None
    """which Mondrian stratum answered: present when the request asked for stratify"""
    t: int = Field(..., title="T")
    """rank of the threshold among them (0: unbounded): `floor((n+1) * epsilon)` without delta, with delta the largest t up to that with pac_failure_probability <= delta"""


class KeypointOut(Frozen):
    guarantee: Guarantee
    index: int = Field(..., title="Index")
    name: str = Field(..., title="Name")
    point: tuple[float, float] = Field(..., title="Point")
    """point estimate in image pixels (the set's centre)"""
    set: BallSet | EllipseSet | UnboundedSet = Field(..., discriminator="type", title="KeypointSet")
    statistics: KeypointStatistics | None = None


class KindSizesOut(Frozen):
    area_px2: SizeSummaryOut | None
    """area pi a b, image px^2"""
    n: int = Field(..., title="N")
    """recent sets of this nonconformity function"""
    semi_major_px: SizeSummaryOut | None
    """semi-major axis (a ball's radius), image px"""
    unbounded: int = Field(..., title="Unbounded")
    """of which unbounded (t = 0)"""


class Manifest(Frozen):
    """A validated model manifest (see docs/bring-your-own-model.md)."""

    model_config = ConfigDict(
        extra="forbid",
    )
    crop: CropSpec = Field({"padding": 0.25}, validate_default=True)
    """how much context around the box is cropped"""
    heatmap: HeatmapSpec = Field(
        {"normalization": "anchor", "temperature": 1.0, "top_k": 100}, validate_default=True
    )
    """how heatmaps become probability maps and set statistics"""
    input: InputSpec
    """the network input and how a crop becomes it"""
    keypoints: list[KeypointSpec] = Field(..., min_length=1, title="Keypoints")
    """one entry per output channel"""
    name: str = Field(..., min_length=1, title="Name")
    """model name, reported with every prediction"""
    objects: list[ObjectSpec] = Field(..., min_length=1, title="Objects")
    """the object classes; every keypoint belongs to exactly one"""
    output: OutputSpec
    """the heatmap output"""
    variant: VariantSpec | None = None
    """present in a folder written by `keypoint-service optimize`: which compressed copy of which model this is"""


class ModelInfo(ModelInfoBase):
    execution_providers: list[str] = Field(
        ..., examples=[["CPUExecutionProvider"]], title="Execution Providers"
    )
    """the onnxruntime execution providers the model runs on, in order of preference (CKS_EXECUTION_PROVIDERS)"""
    hash: str = Field(..., title="Hash")
    manifest: Manifest
    name: str = Field(..., title="Name")
    service_version: str = Field(..., title="Service Version")
    """the version of the service (`keypoint-service --version`)"""
    variant: str = Field(..., examples=["original"], title="Variant")
    """`original`, or the `int8` or `float16` variant of `manifest.variant.source_name`"""


class PoseOut(Frozen):
    """The instance's pose set: an estimate inside PURSE and bounds on the error of any pose in it."""

    checks: list[PoseCheckOut] | None = Field(None, title="Checks")
    empty: bool = Field(..., title="Empty")
    """no pose consistent with the sets was found (they likely missed)"""
    inner_bound: SampledBoundOut | None
    inner_bound_note: str | None = Field(None, title="Inner Bound Note")
    """why there is no inner bound, or that it is sampling's alone (the boundary search needs the pose extra's SciPy); absent: the samples and the boundary search made it"""
    largest_violation: float | None = Field(..., title="Largest Violation")
    """the estimate's largest normalised distance (<= 1)"""
    method: Literal["pnp", "pnp+refined-into-set", "sampled", "none"] = Field(..., title="Method")
    outer_bound: OuterBoundOut | None
    rotation: Rotation | None = Field(..., title="Rotation")
    translation: Translation | None = Field(..., title="Translation")


class VersionList(Frozen):
    active_version: int | None = Field(..., title="Active Version")
    model_hash: str = Field(..., title="Model Hash")
    versions: list[VersionSummary] = Field(..., title="Versions")


class AuditReportOut(Frozen):
    advice: str = Field(..., title="Advice")
    """what to do: nothing, or how to recalibrate and with how many images"""
    band_level: float = Field(..., title="Band Level")
    batch: AuditBatchOut
    correction: str = Field(..., title="Correction")
    """the multiple-testing correction of the flags: holm"""
    family_alpha: float = Field(..., title="Family Alpha")
    """family-wise error rate of the flags"""
    flagged: list[FlaggedFigureOut] = Field(..., title="Flagged")
    """most significant first"""
    instances: int = Field(..., title="Instances")
    """instances scored"""
    passed: bool = Field(..., title="Passed")
    """no figure flagged"""
    sections: list[CoverageSectionOut] = Field(..., title="Sections")
    """one per nonconformity, epsilon and scope"""
    tests: int = Field(..., title="Tests")
    """figures tested (exact and pooled)"""
    version: int = Field(..., title="Version")


class DriftOut(Frozen):
    alarm: bool = Field(..., title="Alarm")
    """sequential: the evidence reached its threshold; ks, psi: any keypoint's alarm is raised"""
    alarm_threshold: float = Field(..., title="Alarm Threshold")
    """sequential: CKS_DRIFT_ALARM_LEVEL, at least 1/this looks between false alarms; ks: family-wise error rate of the Holm-corrected alarm; psi: the PSI threshold"""
    evaluated_at: float = Field(..., title="Evaluated At")
    """unix seconds of the evaluation"""
    evidence: float | None = Field(None, title="Evidence")
    """sequential: the larger of the two e-CUSUMs (1: no evidence); the alarm is raised at evidence_threshold = 2 / CKS_DRIFT_ALARM_LEVEL"""
    evidence_threshold: float | None = Field(None, title="Evidence Threshold")
    """sequential: 2 / CKS_DRIFT_ALARM_LEVEL"""
    frames: int | None = Field(None, title="Frames")
    """sequential: frames (requests) recorded by the replicas covered"""
    history: list[HistoryPointOut] = Field(..., title="History")
    """one point a minute, oldest first"""
    independent_looks: int | None = Field(None, title="Independent Looks")
    """sequential: the independent looks the alarm has tested since the reference version became active (a scene's frames are one look); null for ks and psi, which count every frame"""
    keypoints: list[KeypointDriftOut] = Field(..., title="Keypoints")
    objects: list[ObjectDriftOut] = Field(..., title="Objects")
    oldest_share_seconds: float = Field(..., title="Oldest Share Seconds")
    """age of the oldest other replica's contribution (0: this process alone); each writes every CKS_DRIFT_SHARE_SECONDS"""
    process: int = Field(..., title="Process")
    """the worker process that answered (its windows merged with the other replicas')"""
    reason: str | None = Field(..., title="Reason")
    """why there is no reference (null when there is)"""
    recorded: int = Field(..., title="Recorded")
    """live values recorded by the replicas covered"""
    reference_available: bool = Field(..., title="Reference Available")
    reference_version: int | None = Field(..., title="Reference Version")
    """the active calibration version compared with"""
    replicas: int = Field(..., title="Replicas")
    """worker processes and replicas whose windows and looks this answer covers (this one included): those that wrote to the store within 5 x CKS_DRIFT_SHARE_SECONDS"""
    set_sizes: dict[str, KindSizesOut] = Field(..., title="Set Sizes")
    """recent sets per nonconformity function"""
    statistic: Literal["sequential", "ks", "psi"] = Field(..., title="Statistic")
    """the test (CKS_DRIFT_TEST)"""
    window: int = Field(..., title="Window")
    """live instances kept per keypoint (CKS_DRIFT_WINDOW)"""


class InstanceOut(Frozen):
    bbox: tuple[float, float, float, float] = Field(..., title="Bbox")
    keypoints: list[KeypointOut] = Field(..., title="Keypoints")
    object: str = Field(..., title="Object")
    pose: PoseOut | None = None
    """present when the request asked for pose"""


class PredictResponse(Frozen):
    adaptive: AdaptiveOut | None = None
    """present with adaptive sets: the guarantee that applies is this long-run bound"""
    calibration: CalibrationRef
    image: ImageInfo
    instances: list[InstanceOut] = Field(..., title="Instances")
    model: ModelRef
    prediction_id: str | None = Field(None, title="Prediction Id")
    """present when the answer was retained for feedback: POST /v1/feedback/{prediction_id}"""


class AuditOut(Frozen):
    batch_sha256: str = Field(..., title="Batch Sha256")
    created_at: AwareDatetime = Field(..., title="Created At")
    flagged: int = Field(..., title="Flagged")
    """figures flagged"""
    id: int = Field(..., title="Id")
    instances: int = Field(..., title="Instances")
    passed: bool = Field(..., title="Passed")
    report: AuditReportOut
    version: int = Field(..., title="Version")
    """the calibration version audited"""
    who: str = Field(..., title="Who")


class BatchItem(Frozen):
    """The answer for one image of a batch: a result, or the problem that image alone had."""

    problem: Problem | None = None
    """present otherwise"""
    result: PredictResponse | None = None
    """present when status is 200"""
    status: int = Field(..., title="Status")
    """200, or the status this image would have had on POST /v1/predict"""


class BatchResponse(Frozen):
    items: list[BatchItem] = Field(..., title="Items")
    """one per image, in the order image_0, image_1, ..."""
