"""Typed Python client of the conformal keypoint service.

    from keypoint_client import KeypointClient

    with KeypointClient("http://127.0.0.1:8000") as client:
        result = client.predict("scene.jpg", [("duck", [235, 217, 67, 64])], epsilon=0.1)
        keypoint = result.instances[0].keypoints[0]
        keypoint.set.contains([[268.0, 219.0]])  # -> array([ True])

See README.md for the rest: many images per call, pose sets, retries, calibration
administration, coverage audits and drift.
"""

from keypoint_client.admin_models import (
    Activation,
    ActivationLog,
    AuditEntry,
    AuditPage,
    Comparison,
    Job,
    KeypointChange,
    StoreInfo,
    VersionDetail,
    VersionList,
    VersionSummary,
)
from keypoint_client.calls import AuditOptions, PredictOptions, PredictRequest, UploadOptions
from keypoint_client.client import AsyncKeypointClient, KeypointClient, __version__
from keypoint_client.errors import (
    ActivationRefused,
    BadRequest,
    Conflict,
    ConnectionFailed,
    Forbidden,
    InsufficientStorage,
    InvalidInput,
    JobFailed,
    JobWaitTimeout,
    KeypointClientError,
    NotFound,
    PayloadTooLarge,
    ProblemError,
    RequestTimeout,
    ServerError,
    ServiceUnavailable,
    TooManyRequests,
    Unauthorized,
    UnsupportedMediaType,
)
from keypoint_client.images import ImageInput, png_bytes
from keypoint_client.models import (
    Guarantee,
    Instance,
    InstanceRequest,
    Keypoint,
    KeypointStatistics,
    ModelInfo,
    OuterBound,
    Pose,
    PoseCheck,
    PoseCheckResult,
    PoseRequest,
    PredictResult,
    Readiness,
    SampledBound,
)
from keypoint_client.monitoring_models import (
    AuditReport,
    CoverageAudit,
    CoverageAuditList,
    CoverageAuditSummary,
    CoverageFigure,
    Drift,
    FeedbackResult,
    GroupCoverage,
    LiveCoverage,
)
from keypoint_client.retry import RetryPolicy
from keypoint_client.sets import Ball, Ellipse, PredictionSet, Unbounded

__all__ = [
    "Activation",
    "ActivationLog",
    "ActivationRefused",
    "AsyncKeypointClient",
    "AuditEntry",
    "AuditOptions",
    "AuditPage",
    "AuditReport",
    "BadRequest",
    "Ball",
    "Comparison",
    "Conflict",
    "ConnectionFailed",
    "CoverageAudit",
    "CoverageAuditList",
    "CoverageAuditSummary",
    "CoverageFigure",
    "Drift",
    "FeedbackResult",
    "GroupCoverage",
    "LiveCoverage",
    "Ellipse",
    "Forbidden",
    "Guarantee",
    "ImageInput",
    "Instance",
    "InstanceRequest",
    "InvalidInput",
    "Job",
    "JobFailed",
    "JobWaitTimeout",
    "Keypoint",
    "KeypointChange",
    "KeypointClient",
    "KeypointClientError",
    "KeypointStatistics",
    "ModelInfo",
    "NotFound",
    "OuterBound",
    "PayloadTooLarge",
    "Pose",
    "PoseCheck",
    "PoseCheckResult",
    "PoseRequest",
    "PredictOptions",
    "PredictRequest",
    "PredictResult",
    "PredictionSet",
    "ProblemError",
    "Readiness",
    "RequestTimeout",
    "RetryPolicy",
    "SampledBound",
    "ServerError",
    "ServiceUnavailable",
    "TooManyRequests",
    "InsufficientStorage",
    "StoreInfo",
    "Unauthorized",
    "Unbounded",
    "UnsupportedMediaType",
    "UploadOptions",
    "VersionDetail",
    "VersionList",
    "VersionSummary",
    "__version__",
    "png_bytes",
]
