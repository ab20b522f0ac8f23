"""The client's models mirror the API: the same fields, and the same of them required, as the
committed openapi/openapi.json (and the batch endpoint is in it). The document lists fields
sorted; their order, which the CLI's output keeps, is checked by its test."""

from __future__ import annotations

import json

import keypoint_client as kc
import pytest
from keypoint_client import calls
from pydantic import BaseModel

from service.infra.settings import PACKAGE_ROOT

COMPONENTS = json.loads((PACKAGE_ROOT / "openapi" / "openapi.json").read_text())["components"]["schemas"]
MIRRORS: dict[str, type[BaseModel]] = {
    "PredictResponse": kc.PredictResult,
    "ModelRef": kc.models.ModelRef,
    "CalibrationRef": kc.models.CalibrationRef,
    "ImageInfo": kc.models.ImageInfo,
    "InstanceIn": kc.InstanceRequest,
    "InstanceOut": kc.Instance,
    "KeypointOut": kc.Keypoint,
    "BallSet": kc.Ball,
    "EllipseSet": kc.Ellipse,
    "UnboundedSet": kc.Unbounded,
    "Guarantee": kc.Guarantee,
    "Stratum": kc.models.Stratum,
    "SignalRange": kc.models.SignalRange,
    "BetaLaw": kc.models.BetaLaw,
    "KeypointStatistics": kc.KeypointStatistics,
    "BatchItem": calls._BatchItem,
    "BatchResponse": calls._BatchAnswer,
    "Readiness": kc.Readiness,
    "SourceBatchOut": kc.admin_models.SourceBatch,
    "VersionSummary": kc.VersionSummary,
    "ThresholdRow": kc.admin_models.ThresholdRow,
    "VersionDetail": kc.VersionDetail,
    "VersionList": kc.VersionList,
    "KeypointChangeOut": kc.KeypointChange,
    "ComparisonOut": kc.Comparison,
    "ActivationOut": kc.Activation,
    "ActivationLog": kc.ActivationLog,
    "AuditEntryOut": kc.AuditEntry,
    "AuditPage": kc.AuditPage,
    "StoreInfo": kc.StoreInfo,
    "JobOut": kc.Job,
    "PoseRequest": kc.PoseRequest,
    "PoseCheckIn": kc.PoseCheck,
    "PoseOut": kc.Pose,
    "SampledBoundOut": kc.SampledBound,
    "OuterBoundOut": kc.OuterBound,
    "PoseCheckOut": kc.PoseCheckResult,
    "CoverageFigureOut": kc.CoverageFigure,
    "ObjectCoverageOut": kc.monitoring_models.ObjectCoverage,
    "KeypointCoverageOut": kc.monitoring_models.KeypointCoverage,
    "CoverageSectionOut": kc.monitoring_models.CoverageSection,
    "FlaggedFigureOut": kc.monitoring_models.FlaggedFigure,
    "AuditBatchOut": kc.monitoring_models.AuditBatch,
    "AuditReportOut": kc.AuditReport,
    "AuditSummaryOut": kc.CoverageAuditSummary,
    "AuditOut": kc.CoverageAudit,
    "AuditList": kc.CoverageAuditList,
    "FeatureTestOut": kc.monitoring_models.FeatureTest,
    "KeypointDriftOut": kc.monitoring_models.KeypointDrift,
    "ObjectDriftOut": kc.monitoring_models.ObjectDrift,
    "HistoryPointOut": kc.monitoring_models.DriftHistoryPoint,
    "SizeSummaryOut": kc.monitoring_models.SizeSummary,
    "KindSizesOut": kc.monitoring_models.SetSizes,
    "DriftOut": kc.Drift,
    "AdaptiveOut": kc.AdaptiveLevel,
    "JudgedKeypoint": kc.monitoring_models.JudgedKeypoint,
    "FeedbackOut": kc.FeedbackResult,
    "GroupCoverageOut": kc.GroupCoverage,
    "LiveCoverageOut": kc.LiveCoverage,
    "FieldCalibrationOut": kc.FieldCalibration,
}

# Components the client has no model of, and why.
NOT_MIRRORED = {
    "ActivationIn": "activate() takes its fields as arguments",
    "PredictJson": "the client sends multipart (PredictRequest.parts), not base64 JSON",
    "ModelInfo": "mirrored, but its manifest stays a dict: see test_model_info_names_the_schemas_fields",
    **dict.fromkeys(
        ["Manifest", "CropSpec", "HeatmapSpec", "InputSpec", "KeypointSpec", "ObjectSpec", "OutputSpec"],
        "ModelInfo.manifest is the manifest as a dict",
    ),
    "Problem": "raised as a ProblemError (errors.py)",
    "PredictParameters": "PredictRequest.parts writes it as the form's request part",
    "BatchJson": "predict_batch sends the multipart form, not base64 JSON",
    "Health": "the client has no call of /healthz (ready() reads /readyz)",
    **dict.fromkeys(
        ["FrameRequest", "FrameIn", "RegionIn"],
        "keypoint_client.frames.frame_parts writes it from a numpy frame",
    ),
    "FeedbackIn": "send_feedback takes its instances as an argument",
    "InstanceLabelsIn": "send_feedback takes them as dicts",
    "FieldCalibrationIn": "calibrate_from_feedback takes its fields as arguments",
}


def test_every_component_is_mirrored_or_said_why_not() -> None:
    assert set(COMPONENTS) - set(MIRRORS) == set(NOT_MIRRORED), "a new component of the API: mirror it"


@pytest.mark.parametrize("component", sorted(MIRRORS))
def test_the_model_mirrors_the_schema(component: str) -> None:
    schema, model = COMPONENTS[component], MIRRORS[component]
    assert set(model.model_fields) == set(schema["properties"]), model
    required = {name for name, field in model.model_fields.items() if field.is_required()}
    assert required == set(schema.get("required", [])), model


def test_a_problem_error_reads_every_member_of_the_problem_schema() -> None:
    assert set(COMPONENTS["Problem"]["properties"]) == kc.errors.PROBLEM_MEMBERS


def test_model_info_names_the_schemas_fields() -> None:
    assert set(kc.ModelInfo.model_fields) == set(COMPONENTS["ModelInfo"]["properties"])


def test_the_batch_endpoint_is_documented() -> None:
    """The client posts its multipart batch to /v1/predict/batch, which takes the form at run time
    as it always did; the document describes that form at /v1/predict/batch/form (docs/api.md)."""
    paths = json.loads((PACKAGE_ROOT / "openapi" / "openapi.json").read_text())["paths"]
    batch = paths["/v1/predict/batch/form"]["post"]
    assert list(batch["requestBody"]["content"]) == ["multipart/form-data"]
    assert batch["responses"]["200"]["content"]["application/json"]["schema"]["$ref"].endswith(
        "/BatchResponse"
    )
