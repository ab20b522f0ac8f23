"""Every call of the API as data: what to send, whether it may be repeated, how to read the
answer. The synchronous and the asynchronous client only send these and wait."""

from __future__ import annotations

import json
import time
from collections.abc import Callable, Iterator, Mapping, Sequence
from dataclasses import dataclass, field
from pathlib import Path
from typing import TYPE_CHECKING, Any, Generic, Literal, TypedDict, TypeVar
from urllib.parse import quote

import httpx
from pydantic import BaseModel

from keypoint_client import generated_models as api
from keypoint_client.errors import JobFailed, JobWaitTimeout, KeypointClientError, ProblemError, problem_error
from keypoint_client.frames import FrameSending, frame_parts, is_frame
from keypoint_client.images import ChannelOrder, ImageInput, encode_image
from keypoint_client.models import (
    Activation,
    ActivationLog,
    AuditPage,
    Comparison,
    CoverageAudit,
    CoverageAuditList,
    Drift,
    FeedbackResult,
    FieldCalibration,
    InstanceLike,
    Job,
    LiveCoverage,
    ModelInfo,
    PoseRequest,
    PredictResult,
    Readiness,
    StoreInfo,
    VersionDetail,
    VersionList,
    instance_request,
)
from keypoint_client.retry import retry_after_seconds

if TYPE_CHECKING:
    from typing import Unpack

    from numpy.typing import NDArray

T = TypeVar("T")
M = TypeVar("M", bound=BaseModel)
Files = list[tuple[str, tuple[str | None, bytes, str]]]
Params = Mapping[str, str | list[str]]
Reader = Callable[[httpx.Response, str], T]
DEFAULT_BATCH_SIZE = 16  # the most images the service takes in one batch
# The values the document lists for these options of a prediction.
Nonconformity = Literal["peak", "var", "cov"]
Coverage = Literal["keypoint", "object"]
Stratify = Literal["none", "difficulty", "group", "difficulty+group"]
GroupFallback = Literal["refuse", "pooled"]


class PredictOptions(TypedDict, total=False):
    """Options of ``predict`` (and fields of ``PredictRequest``); see ``PredictRequest``."""

    epsilon: float
    nonconformity: Nonconformity
    coverage: Coverage
    delta: float | None
    calibration_version: int | None
    include_statistics: bool
    channel_order: ChannelOrder
    pose: PoseRequest | None
    retain: bool
    stream: str | None
    adaptive: bool
    stratify: Stratify
    group_fallback: GroupFallback


@dataclass(frozen=True)
class PredictRequest:
    """One image and what to predict for it.

    ``epsilon``: each set misses its keypoint with probability at most this. ``nonconformity``:
    ``peak`` and ``var`` give balls, ``cov`` ellipses. ``coverage``: ``keypoint`` (each keypoint)
    or ``object`` (all of an object's keypoints at once). ``delta``: PAC, the guarantee holds
    with probability 1 - delta over the calibration set. ``calibration_version``: default the
    active one. ``include_statistics``: add the raw heatmap statistics. ``channel_order``: of a
    numpy image's colour channels (``"bgr"`` for OpenCV's). ``pose``: also each instance's pose
    set, from the camera matrix (needs ``coverage="object"``; see ``PoseRequest``).
    ``stratify``: Mondrian strata (``difficulty``, ``group`` from each instance's ``group``, or
    both), each keypoint's guarantee then conditional on its stratum; ``group_fallback``: where a
    keypoint has no bounded stratum, ``refuse`` (a 422) or use the ``pooled`` threshold.
    """

    image: ImageInput
    instances: Sequence[InstanceLike]
    epsilon: float = 0.1
    nonconformity: Nonconformity = "cov"
    coverage: Coverage = "keypoint"
    delta: float | None = None
    calibration_version: int | None = None
    include_statistics: bool = False
    channel_order: ChannelOrder = "rgb"
    pose: PoseRequest | None = None
    retain: bool = False
    stream: str | None = None
    adaptive: bool = False
    stratify: Stratify = "none"
    group_fallback: GroupFallback = "refuse"

    def parts(self, suffix: str = "") -> Files:
        """The multipart parts ``image<suffix>`` and ``request<suffix>``."""
        encoded = encode_image(self.image, self.channel_order)
        return [
            (f"image{suffix}", (encoded.filename, encoded.data, encoded.content_type)),
            (f"request{suffix}", (None, json.dumps(self.parameters()).encode(), "application/json")),
        ]

    def parameters(self) -> dict[str, Any]:
        """The request's JSON: its instances and options."""
        parameters = {
            "instances": [instance_request(instance).to_dict() for instance in self.instances],
            "epsilon": self.epsilon,
            "nonconformity": self.nonconformity,
            "coverage": self.coverage,
            "delta": self.delta,
            "calibration_version": self.calibration_version,
            "include_statistics": self.include_statistics,
            "pose": None if self.pose is None else self.pose.to_dict(),
        }
        if self.retain:  # sent only when asked: servers before feedback refuse unknown fields
            parameters["retain"] = True
        if self.stream is not None:
            parameters["stream"] = self.stream
        if self.adaptive:
            parameters["adaptive"] = True
        if self.stratify != "none":
            parameters["stratify"] = self.stratify
        if self.group_fallback != "refuse":
            parameters["group_fallback"] = self.group_fallback
        return parameters


class UploadOptions(TypedDict, total=False):
    """Options of a calibration upload: ``name`` of the batch, ``note`` stored with the version,
    ``append_to`` a version (new version = it + the batch), ``activate`` when the job succeeds
    (``force`` past the guardrails, with a ``reason``), ``dedupe`` (drop instances already
    counted instead of refusing), ``max_rejected_share`` of instances the box rule may reject."""

    name: str
    note: str
    append_to: int
    activate: bool
    force: bool
    reason: str
    dedupe: bool
    max_rejected_share: float


class AuditOptions(TypedDict, total=False):
    """Options of a coverage audit: the ``version`` to audit (default the active one), the
    ``epsilon`` values to audit at (default 0.05, 0.1 and 0.2), ``name`` and ``note`` of the
    batch, ``dedupe`` (drop instances the version was calibrated with instead of refusing),
    ``max_rejected_share`` of instances the box rule may reject."""

    version: int
    epsilon: Sequence[float]
    name: str
    note: str
    dedupe: bool
    max_rejected_share: float


@dataclass(frozen=True)
class Call(Generic[T]):
    """One exchange with the service. ``upload`` is a file streamed as the body."""

    method: str
    path: str
    read: Reader[T]
    idempotent: bool = True
    params: Params | None = None
    json: Any = None
    files: Files | None = None
    upload: Path | None = None
    headers: dict[str, str] = field(default_factory=dict)
    timeout: float | None = None

    def request_arguments(self, request_id: str) -> dict[str, Any]:
        """Keyword arguments of httpx's ``request`` for one attempt, but the streamed ``content``."""
        return {
            "method": self.method,
            "url": self.path,
            "params": self.params,
            "json": self.json,
            "files": self.files,
            "headers": {**self.headers, "X-Request-ID": request_id},
            "timeout": httpx.USE_CLIENT_DEFAULT if self.timeout is None else self.timeout,
        }

    def answer(self, response: httpx.Response, request_id: str) -> T:
        """The result, or the service's problem raised as a typed exception."""
        if response.is_error:
            raise problem_from(response, request_id)
        return self.read(response, request_id)


def problem_from(response: httpx.Response, request_id: str) -> ProblemError:
    try:
        body = response.json()
    except ValueError:
        body = None
    if not isinstance(body, dict):  # not problem+json: a proxy's page, say
        text = response.text.strip()[:500]
        body = {"title": response.reason_phrase or "Error", "detail": text or f"HTTP {response.status_code}"}
    retry_after = retry_after_seconds(response.headers.get("retry-after"))
    request_id = response.headers.get("x-request-id") or request_id
    return problem_error(response.status_code, body, request_id, retry_after)


def _model(kind: type[M]) -> Reader[M]:
    return lambda response, _: kind.model_validate_json(response.content)


def _flag(value: bool) -> str:
    return "true" if value else "false"


# ---------------------------------------------------------------- prediction


def predict(
    image: ImageInput,
    instances: Sequence[InstanceLike],
    *,
    timeout: float | None = None,
    **options: Unpack[PredictOptions],
) -> Call[PredictResult]:
    """Prediction sets for one image: JPEG or PNG bytes, a path to one, or a numpy array.
    ``instances``: the objects and their boxes. Options: see ``PredictRequest``."""
    return _predict_json("/v1/predict", PredictRequest(image, instances, **options).parts(), timeout)


def predict_any(
    image: ImageInput,
    instances: Sequence[InstanceLike],
    padding: float | None,
    sending: FrameSending = "regions",
    *,
    timeout: float | None = None,
    **options: Unpack[PredictOptions],
) -> Call[PredictResult]:
    """``predict_frame`` for a numpy frame (given the model's crop ``padding``), else ``predict``."""
    if is_frame(image) and padding is not None:
        return predict_frame(image, instances, padding, sending, timeout=timeout, **options)
    return predict(image, instances, timeout=timeout, **options)


def predict_frame(
    frame: NDArray[Any],
    instances: Sequence[InstanceLike],
    padding: float,
    sending: FrameSending = "regions",
    *,
    timeout: float | None = None,
    **options: Unpack[PredictOptions],
) -> Call[PredictResult]:
    """Prediction sets for a numpy frame of uint8 pixels through POST /v1/predict/frame, sent as
    ``sending`` says (``keypoint_client.frames``); ``padding``: the model manifest's crop padding."""
    request = PredictRequest(frame, instances, **options)
    files = frame_parts(frame, request.parameters(), padding, sending, request.channel_order)
    return _predict_json("/v1/predict/frame", files, timeout)


def _predict_json(path: str, files: Files, timeout: float | None) -> Call[PredictResult]:
    return Call(
        "POST",
        path,
        _model(PredictResult),
        files=files,
        headers={"Accept": "application/json"},
        timeout=timeout,
    )


def predict_png(
    image: ImageInput,
    instances: Sequence[InstanceLike],
    *,
    timeout: float | None = None,
    **options: Unpack[PredictOptions],
) -> Call[bytes]:
    """The image with its prediction sets drawn on it, as PNG bytes (arguments as ``predict``)."""
    files = PredictRequest(image, instances, **options).parts()
    return Call(
        "POST",
        "/v1/predict",
        lambda response, _: response.content,
        files=files,
        headers={"Accept": "image/png"},
        timeout=timeout,
    )


def predict_batch(
    requests: Sequence[PredictRequest], timeout: float | None
) -> Call[list[PredictResult | ProblemError]]:
    def read(response: httpx.Response, request_id: str) -> list[PredictResult | ProblemError]:
        items = api.BatchResponse.model_validate_json(response.content).items
        if len(items) != len(requests):
            raise KeypointClientError(f"the service answered {len(items)} items for {len(requests)} images")
        return [
            item.result
            if item.status == 200 and item.result is not None
            else problem_error(item.status, item.problem.to_dict() if item.problem else {}, request_id)
            for item in items
        ]

    files = [part for index, request in enumerate(requests) for part in request.parts(f"_{index}")]
    return Call("POST", "/v1/predict/batch", read, files=files, timeout=timeout)


def batches(requests: Sequence[PredictRequest], size: int) -> Iterator[Sequence[PredictRequest]]:
    if size < 1:
        raise ValueError(f"batch_size must be at least 1, not {size}")
    for start in range(0, len(requests), size):
        yield requests[start : start + size]


def model(*, timeout: float | None = None) -> Call[ModelInfo]:
    """The served model: its name, hash and manifest (objects and keypoints)."""
    return Call("GET", "/v1/model", _model(ModelInfo), timeout=timeout)


def ready(*, timeout: float | None = None) -> Call[Readiness]:
    """The service is ready (model loaded, store reachable, a calibration active); else ServiceUnavailable."""
    return Call("GET", "/readyz", _model(Readiness), timeout=timeout)


# ---------------------------------------------------------------- administration


def _query(value: object) -> str | list[str]:
    """An option as query text: a flag, numbers repeated (an audit's epsilons), or as it prints."""
    if isinstance(value, bool):
        return _flag(value)
    if isinstance(value, Sequence) and not isinstance(value, str):
        return [repr(float(item)) for item in value]
    return str(value)


def _zip_upload(path: str, archive: Path, options: Mapping[str, object], timeout: float | None) -> Call[Job]:
    params = {key: _query(value) for key, value in options.items()}
    headers = {"Content-Type": "application/zip", "Content-Length": str(archive.stat().st_size)}
    return Call(
        "POST",
        path,
        _model(Job),
        idempotent=False,
        params=params,
        upload=archive,
        headers=headers,
        timeout=timeout,
    )


def upload(archive: Path, options: UploadOptions, timeout: float | None) -> Call[Job]:
    return _zip_upload("/v1/admin/calibrations", archive, options, timeout)


def start_audit(archive: Path, options: AuditOptions, timeout: float | None) -> Call[Job]:
    return _zip_upload("/v1/admin/audits", archive, options, timeout)


def job(job: str | Job, *, timeout: float | None = None) -> Call[Job]:
    """A calibration job's state, progress and errors (any replica answers)."""
    return Call("GET", f"/v1/admin/jobs/{_job_id(job)}", _model(Job), timeout=timeout)


def retry_job(job: str | Job, *, timeout: float | None = None) -> Call[Job]:
    """Run an interrupted job again from its kept upload; returns the new job."""
    path = f"/v1/admin/jobs/{_job_id(job)}/retry"
    return Call("POST", path, _model(Job), idempotent=False, timeout=timeout)


def _job_id(job: str | Job) -> str:
    return quote(job if isinstance(job, str) else job.id, safe="")


def versions(*, timeout: float | None = None) -> Call[VersionList]:
    """Every calibration version of the served model, and which is active."""
    return Call("GET", "/v1/admin/calibrations", _model(VersionList), timeout=timeout)


def version(number: int, *, timeout: float | None = None) -> Call[VersionDetail]:
    """One version in detail: n per keypoint, thresholds, whether the manifest can serve it."""
    return Call("GET", f"/v1/admin/calibrations/{int(number)}", _model(VersionDetail), timeout=timeout)


def compare(
    number: int,
    *,
    against: Literal["active"] | int = "active",
    epsilon: float = 0.1,
    nonconformity: Nonconformity = "cov",
    timeout: float | None = None,
) -> Call[Comparison]:
    """Dry run: a version against the active one (or ``against``), and whether activating it is allowed."""
    params = {"against": str(against), "epsilon": repr(float(epsilon)), "nonconformity": nonconformity}
    path = f"/v1/admin/calibrations/{int(number)}/compare"
    return Call("GET", path, _model(Comparison), params=params, timeout=timeout)


def activate(
    number: int, *, reason: str = "", force: bool = False, timeout: float | None = None
) -> Call[Activation]:
    """Make a version active (an older one: a rollback). ActivationRefused, with the comparison,
    when the guardrails refuse; ``force=True`` with a ``reason`` overrides them (audited)."""
    path = f"/v1/admin/calibrations/{int(number)}/activate"
    body = {"reason": reason, "force": force}
    return Call("POST", path, _model(Activation), idempotent=False, json=body, timeout=timeout)


def activations(*, timeout: float | None = None) -> Call[ActivationLog]:
    """The append-only activation history, oldest first."""
    return Call("GET", "/v1/admin/activations", _model(ActivationLog), timeout=timeout)


def audit(*, before: int | None = None, limit: int = 100, timeout: float | None = None) -> Call[AuditPage]:
    """A page of the audit trail, newest first; pass ``next_before`` as ``before`` for the next page."""
    params = {"limit": str(limit)} | ({} if before is None else {"before": str(before)})
    return Call("GET", "/v1/admin/audit", _model(AuditPage), params=params, timeout=timeout)


def audits(
    *, before: int | None = None, limit: int = 100, timeout: float | None = None
) -> Call[CoverageAuditList]:
    """A page of the coverage audits of the served model, newest first; pass ``next_before`` as
    ``before`` for the next page."""
    params = {"limit": str(limit)} | ({} if before is None else {"before": str(before)})
    return Call("GET", "/v1/admin/audits", _model(CoverageAuditList), params=params, timeout=timeout)


def coverage_audit(audit: int | Job, *, timeout: float | None = None) -> Call[CoverageAudit]:
    """One coverage audit, by its id or by the job that made it: every figure with its band and
    p-value, the flagged ones (Holm) and the advice."""
    path = f"/v1/admin/audits/{_audit_id(audit)}"
    return Call("GET", path, _model(CoverageAudit), timeout=timeout)


def _audit_id(audit: int | Job) -> int:
    if isinstance(audit, int):
        return audit
    if audit.kind != "audit" or "audit" not in audit.result:
        raise ValueError(f"job {audit.id} ({audit.kind}, {audit.state}) has made no coverage audit")
    return int(audit.result["audit"])


def drift(*, timeout: float | None = None) -> Call[Drift]:
    """The live heatmap features of every keypoint tested against the active calibration's, for
    every worker process and replica sharing the store (``replicas``). NotFound when the
    server's drift monitoring is off."""
    return Call("GET", "/v1/admin/drift", _model(Drift), timeout=timeout)


def send_feedback(
    prediction_id: str, instances: Sequence[Mapping[str, Any]], *, timeout: float | None = None
) -> Call[FeedbackResult]:
    """The true points of a retained prediction (``predict(..., retain=True)``'s ``prediction_id``):
    ``instances`` as ``{"instance": i, "keypoints": [[x, y, v], ...]}`` (v = 0: not labelled). Needs
    a feedback or admin token; ProblemError 404 (unknown), 409 (labelled already), 410 (expired)."""
    body = {"instances": [dict(instance) for instance in instances]}
    path = f"/v1/feedback/{quote(prediction_id, safe='')}"
    return Call("POST", path, _model(FeedbackResult), idempotent=False, json=body, timeout=timeout)


def live_coverage(*, timeout: float | None = None) -> Call[LiveCoverage]:
    """The coverage the feedback labels show, per version, object, keypoint, stream and group, with
    an anytime-valid confidence sequence and the alarm when coverage is proven below the promise."""
    return Call("GET", "/v1/admin/coverage/live", _model(LiveCoverage), timeout=timeout)


def calibrate_from_feedback(
    *,
    stream: str | None = None,
    served_by: int | None = None,
    name: str | None = None,
    note: str = "",
    append_to: int | None = None,
    activate: bool = False,
    force: bool = False,
    reason: str = "",
    dedupe: bool = False,
    allow_duplicate: bool = False,
    timeout: float | None = None,
) -> Call[FieldCalibration]:
    """A calibration version from the labelled feedback (no zip). Which labels: a camera
    ``stream``'s only, those of answers ``served_by`` a version only (default every label).
    ``name`` of the source batch (default feedback-<sha256>), ``note`` stored with the version,
    ``append_to`` a version (new version = it + the labels), ``activate`` it (``force`` past the
    guardrails, with a ``reason``), ``dedupe`` (drop instances already counted instead of
    refusing), ``allow_duplicate`` (store a version equal to a stored one). Conflict for repeats
    or a version equal to a stored one; InvalidInput when no labelled feedback matches."""
    body = api.FieldCalibrationIn(
        stream=stream,
        served_by=served_by,
        name=name,
        note=note,
        append_to=append_to,
        activate=activate,
        force=force,
        reason=reason,
        dedupe=dedupe,
        allow_duplicate=allow_duplicate,
    )
    path, read = "/v1/admin/field-calibrations", _model(FieldCalibration)
    return Call("POST", path, read, idempotent=False, json=body.to_dict(), timeout=timeout)


def store(*, timeout: float | None = None) -> Call[StoreInfo]:
    """Which calibration store the server uses, and where."""
    return Call("GET", "/v1/admin/store", _model(StoreInfo), timeout=timeout)


class JobWatch:
    """The decisions of waiting for a job: tell ``progress`` of every change, stop when it is
    finished (JobFailed unless it succeeded) or the wait's ``timeout`` has run out."""

    def __init__(
        self, progress: Callable[[Job], object] | None, poll_interval: float, timeout: float | None
    ) -> None:
        self.progress, self.poll_interval, self.timeout = progress, poll_interval, timeout
        self.deadline = None if timeout is None else time.monotonic() + timeout
        self.last: tuple[str, int, int] | None = None

    def next_poll(self, job: Job) -> float | None:
        """Seconds until the next look, or None: ``job`` succeeded."""
        if (job.state, job.done, job.total) != self.last:
            self.last = (job.state, job.done, job.total)
            if self.progress is not None:
                self.progress(job)
        if job.state == "succeeded":
            return None
        if job.finished:
            raise JobFailed(job)
        if self.deadline is not None and self.timeout is not None and time.monotonic() >= self.deadline:
            raise JobWaitTimeout(job, self.timeout)
        return self.poll_interval
