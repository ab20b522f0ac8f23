"""The bodies of the API under the client's names: the models generated from openapi/openapi.json
(generated_models.py, whose names are the document's), with the methods of bases.py and sets.py."""

from __future__ import annotations

from collections.abc import Mapping, Sequence
from typing import Any

from keypoint_client import generated_models as api

# prediction
InstanceRequest = api.InstanceIn
PredictResult = api.PredictResponse
Instance = api.InstanceOut
Keypoint = api.KeypointOut
Ball, Ellipse, Unbounded = api.BallSet, api.EllipseSet, api.UnboundedSet
PredictionSet = Ball | Ellipse | Unbounded
Guarantee = api.Guarantee
KeypointStatistics = api.KeypointStatistics
AdaptiveLevel = api.AdaptiveOut
PoseRequest = api.PoseRequest
PoseCheck = api.PoseCheckIn
Pose = api.PoseOut
SampledBound = api.SampledBoundOut
OuterBound = api.OuterBoundOut
PoseCheckResult = api.PoseCheckOut
ModelInfo = api.ModelInfo
Readiness = api.Readiness

# administration
Job = api.JobOut
VersionSummary = api.VersionSummary
VersionDetail = api.VersionDetail
VersionList = api.VersionList
Comparison = api.ComparisonOut
KeypointChange = api.KeypointChangeOut
Activation = api.ActivationOut
ActivationLog = api.ActivationLog
AuditEntry = api.AuditEntryOut
AuditPage = api.AuditPage
StoreInfo = api.StoreInfo

# monitoring and feedback
AuditReport = api.AuditReportOut
CoverageAudit = api.AuditOut
CoverageAuditSummary = api.AuditSummaryOut
CoverageAuditList = api.AuditList
CoverageFigure = api.CoverageFigureOut
Drift = api.DriftOut
FeedbackResult = api.FeedbackOut
GroupCoverage = api.GroupCoverageOut
LiveCoverage = api.LiveCoverageOut
FieldCalibration = api.FieldCalibrationOut

# An instance as InstanceRequest, ("duck", [x, y, w, h]) or {"object": "duck", "bbox": [x, y, w, h]}.
InstanceLike = InstanceRequest | tuple[str, Sequence[float]] | Mapping[str, Any]


def instance_request(instance: InstanceLike) -> InstanceRequest:
    if isinstance(instance, InstanceRequest):
        return instance
    if isinstance(instance, tuple):
        name, bbox = instance
        return InstanceRequest.model_validate({"object": name, "bbox": bbox})
    return InstanceRequest.model_validate(instance)
