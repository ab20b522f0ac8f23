"""All configuration, from environment variables prefixed ``CKS_`` (see README, Configuration)."""

from __future__ import annotations

import json
from collections.abc import Mapping
from functools import cached_property
from pathlib import Path
from typing import Annotated, Literal

from pydantic import Field, field_validator
from pydantic_settings import BaseSettings, NoDecode, SettingsConfigDict

from calibration_store import sqlite_path
from service.conformal.features import HEATMAP_FEATURES

PACKAGE_ROOT = Path(__file__).resolve().parent.parent
DEFAULT_MODEL_DIR = PACKAGE_ROOT / "models" / "lmo-synth-unet"

_ONE_RUN = (
    "micro-batching was removed (it lost on CPU and GPU, see CHANGELOG); each request's crops are one"
    " run on its own thread, with CKS_INFERENCE_THREADS intra-op threads"
)
#: Settings no longer read, which an operator may still set: what replaced each.
REMOVED_SETTINGS = {
    "CKS_MAX_INFERENCE_BATCH": _ONE_RUN,
    "CKS_INFERENCE_STREAMS": _ONE_RUN,
    "CKS_BATCH_WINDOW_MS": _ONE_RUN,
    "CKS_SOLO_INFERENCE_THREADS": "the lone-request session was removed (it did not pay, see CHANGELOG);"
    " every run has CKS_INFERENCE_THREADS intra-op threads",
}


def removed_settings(environ: Mapping[str, str]) -> list[str]:
    """One line for each removed setting that ``environ`` still sets."""
    return [f"{name} is no longer read: {why}" for name, why in REMOVED_SETTINGS.items() if name in environ]


class Settings(BaseSettings):
    """Service settings. Every field is an environment variable ``CKS_<FIELD>``."""

    model_config = SettingsConfigDict(env_prefix="CKS_", extra="ignore", frozen=True)

    model_dir: Path = Field(
        default=DEFAULT_MODEL_DIR, description="directory with model.onnx and manifest.json"
    )
    data_dir: Path = Field(
        default=Path("var"),
        description="where the service writes (SQLite store, uploads, metrics files of several workers)",
    )
    store_url: str | None = Field(
        default=None, description="sqlite:///path or postgresql://...; default sqlite under data_dir"
    )
    admin_token: str | None = Field(
        default=None, description="bearer token for /v1/admin (operator 'admin'); unset disables it"
    )
    admin_tokens_file: Path | None = Field(
        default=None, description="file of 'name:token' lines: named admin operators for the audit trail"
    )
    bootstrap_calibration: bool = Field(
        default=True, description="load the model's bundled calibration as version 1 when the store has none"
    )

    host: str = Field(default="127.0.0.1", description="address to listen on")
    port: int = Field(default=8000, ge=1, le=65535, description="port to listen on")
    workers: int = Field(
        default=1, ge=1, le=64, description="uvicorn worker processes (limits below are per process)"
    )
    max_connections: int = Field(
        default=1000, ge=1, description="open connections per process; a request beyond gets 503"
    )
    header_read_timeout_seconds: float = Field(
        default=10.0,
        gt=0,
        description="longest time for a request's line and headers to arrive (408 and closed beyond)",
    )
    min_body_bytes_per_second: float = Field(
        default=1024.0,
        gt=0,
        description="slowest average rate a request body may arrive at, after the grace below (408 below)",
    )
    body_rate_grace_seconds: float = Field(
        default=5.0, gt=0, description="time a request body gets before its average rate is checked"
    )
    shutdown_grace_seconds: float = Field(
        default=20.0,
        ge=0,
        description="on SIGTERM, longest wait for in-flight requests before running jobs are interrupted",
    )

    max_request_bytes: int = Field(default=20 * 2**20, gt=0, description="largest predict request body")
    max_image_pixels: int = Field(default=40_000_000, gt=0, description="largest width*height decoded")
    max_instances: int = Field(default=64, gt=0, description="instances per predict request")
    max_batch_images: int = Field(
        default=16,
        gt=0,
        le=1024,
        description="images per POST /v1/predict/batch request (each takes one admission place;"
        " the body obeys CKS_MAX_REQUEST_BYTES)",
    )
    max_concurrent_inferences: int = Field(default=8, gt=0, description="predict requests computing at once")
    max_queued_requests: int = Field(
        default=32, ge=0, description="predict requests waiting for a slot; more get 503 at once"
    )
    request_read_timeout_seconds: float = Field(
        default=30.0, gt=0, description="longest time to receive a predict request body (408 beyond)"
    )
    max_receiving_bytes: int = Field(
        default=256 * 2**20,
        gt=0,
        description="bytes of predict bodies being received at once, all requests together (503 beyond)",
    )
    max_decoded_bytes: int = Field(
        default=256 * 2**20,
        gt=0,
        description="memory one image may take to decode (its real bytes: 16-bit, alpha); 413 beyond",
    )
    queue_timeout_seconds: float = Field(
        default=10.0, gt=0, description="longest wait for a slot before a predict request gets 503"
    )
    inference_threads: int = Field(
        default=1, ge=0, description="onnxruntime intra-op threads per run (0 = ort default)"
    )
    cpu_workers: int = Field(
        default=4, gt=0, description="threads for decode, crop and scoring off the event loop"
    )
    execution_providers: Annotated[tuple[str, ...], NoDecode] = Field(
        default=("CPUExecutionProvider",),
        description="onnxruntime execution providers in order of preference, comma-separated or a JSON"
        " list, e.g. CUDAExecutionProvider,CPUExecutionProvider (GPU: the gpu extra, docs/operations.md);"
        " one that this onnxruntime lacks is refused at start-up",
    )
    execution_provider_options: dict[str, dict[str, str]] = Field(
        default_factory=dict,
        description='JSON options per provider, e.g. {"CUDAExecutionProvider": {"device_id": "1"}}',
    )
    max_upload_bytes: int = Field(default=2 * 2**30, gt=0, description="largest calibration zip")
    max_upload_files: int = Field(default=100_000, gt=0, description="most files in a calibration zip")
    max_upload_uncompressed_bytes: int = Field(
        default=4 * 2**30, gt=0, description="most bytes once unzipped"
    )
    upload_read_timeout_seconds: float = Field(
        default=3600.0, gt=0, description="longest time to receive a calibration upload (408 beyond)"
    )
    max_uploads_disk_bytes: int = Field(
        default=16 * 2**30,
        gt=0,
        description="disk kept uploads (zips, unzipped batches of unfinished jobs) may take (507 beyond)",
    )
    min_free_disk_bytes: int = Field(
        default=2**30,
        ge=0,
        description="free space that unzipping an upload must leave in the data directory (507 beyond)",
    )
    calibration_workers: int = Field(default=1, gt=0, description="calibration jobs running at once")
    min_calibration_instances: int = Field(
        default=100, ge=0, description="activation needs this n per keypoint (unless forced with a reason)"
    )
    stratum_signals: str = Field(
        default="gamma,peak_probability",
        description="difficulty strata: one heatmap feature, or two (comma-separated) for joint bins"
        " (peak_probability, gamma, anisotropy)",
    )
    stratum_bins: int = Field(
        default=3, ge=1, le=20, description="difficulty strata: quantile bins per signal"
    )
    min_stratum_instances: int = Field(
        default=30, ge=1, description="difficulty strata: least calibration scores per bin (bins merge below)"
    )
    max_rejected_share: float = Field(
        default=0.0, ge=0, le=1, description="share of a batch's instances that may be rejected (default)"
    )

    store_poll_seconds: float = Field(
        default=1.0, gt=0, description="how often to look for a new active version"
    )
    store_timeout_seconds: float = Field(
        default=1.5,
        gt=0,
        description="longest wait for a PostgreSQL store connection; beyond it the store counts as"
        " unreachable (admin calls answer 503, predictions go on from memory)",
    )
    max_cache_staleness_seconds: float | None = Field(
        default=None,
        gt=0,
        description="/readyz answers 503 once the store has not confirmed the cached calibration for"
        " this long; unset: never (predictions go on either way)",
    )

    drift_enabled: bool = Field(
        default=True,
        description="keep windows of every keypoint's live heatmap features and test them against the"
        " active calibration's (GET /v1/admin/drift, cks_drift_* metrics)",
    )
    drift_window: int = Field(
        default=500,
        ge=10,
        le=100_000,
        description="live instances kept per keypoint (the drift window; each feature's window holds"
        " those that computed it)",
    )
    drift_test: Literal["ks", "psi"] = Field(
        default="ks",
        description="drift test: `ks` (Kolmogorov-Smirnov p-values, Holm-corrected) or `psi` (population"
        " stability index over 10 quantile bins)",
    )
    drift_alarm_level: float = Field(
        default=0.01,
        gt=0,
        lt=1,
        description="ks: family-wise error rate of the drift alarm over all keypoints x features (Holm)",
    )
    drift_psi_threshold: float = Field(
        default=0.25,
        gt=0,
        description="psi: a keypoint's feature alarms above this index (once it has 400 live values)",
    )
    drift_full_statistics_share: float = Field(
        default=0.25,
        ge=0,
        le=1,
        description="share of predictions that also compute the heatmap statistics their nonconformity"
        " function skips, so every drift feature gets live values (the rest record theirs for free)",
    )
    drift_history_seconds: float = Field(
        default=60.0, gt=0, description="one point of the drift history this often (360 points kept)"
    )

    log_format: Literal["text", "json"] = Field(
        default="text",
        description="`text` (one line: UTC time, level, logger, [request id], message) or `json`"
        " (one JSON object a line), for the service's lines and uvicorn's alike",
    )
    log_level: Literal["DEBUG", "INFO", "WARNING", "ERROR"] = Field(
        default="INFO",
        description="least severe level logged by `serve`; the other commands log warnings and errors"
        " only unless it is set",
    )
    access_log: bool = Field(
        default=True,
        description="one line per request: method, path, status, latency, request id, calibration version",
    )

    @field_validator("stratum_signals")
    @classmethod
    def _stratum_signals(cls, value: str) -> str:
        names = [name.strip() for name in value.split(",") if name.strip()]
        unknown = [name for name in names if name not in HEATMAP_FEATURES]
        if not 1 <= len(names) <= 2 or unknown or len(set(names)) != len(names):
            raise ValueError(f"give one or two distinct heatmap features of {', '.join(HEATMAP_FEATURES)},"
                             f" comma-separated; got {value!r}")  # fmt: skip
        return ",".join(names)

    @field_validator("log_level", mode="before")
    @classmethod
    def _upper(cls, level: object) -> object:
        return level.upper() if isinstance(level, str) else level

    @field_validator("execution_providers", mode="before")
    @classmethod
    def _provider_list(cls, providers: object) -> object:
        """``A,B`` or ``["A", "B"]``; whether this onnxruntime has them is checked when the model loads."""
        if isinstance(providers, str) and providers.strip().startswith("["):
            try:
                providers = json.loads(providers)
            except json.JSONDecodeError as error:
                raise ValueError(f"not a JSON list ({error}); or names separated by commas") from None
        elif isinstance(providers, str):
            providers = [name.strip() for name in providers.split(",") if name.strip()]
        if isinstance(providers, list | tuple) and not providers:
            raise ValueError("name at least one, e.g. CPUExecutionProvider")
        if isinstance(providers, list | tuple) and len(set(map(str, providers))) < len(providers):
            raise ValueError("a provider is named twice: name each once, in order of preference")
        return providers

    @field_validator("store_url")
    @classmethod
    def _known_store(cls, url: str | None) -> str | None:
        """Refused when the settings are read, naming the setting, not when the store is opened."""
        if url is None:
            return None
        scheme = url.partition(":")[0].lower()
        if scheme == "sqlite":
            sqlite_path(url)  # says what is wrong with a sqlite URL
        elif scheme not in ("postgresql", "postgres"):
            raise ValueError("use sqlite:///path/to/file.db or postgresql://user@host:port/database")
        return url

    @field_validator("data_dir", "model_dir", "admin_tokens_file")
    @classmethod
    def _absolute(cls, path: Path | None) -> Path | None:
        """Resolved once, against the directory the service starts in, and said at start-up."""
        return None if path is None else path.expanduser().resolve()

    @cached_property
    def resolved_store_url(self) -> str:
        if not self.store_url:
            return f"sqlite:///{self.data_dir / 'calibrations.db'}"
        if self.store_url.startswith("sqlite:") and not self.store_url.startswith("sqlite:///"):
            return f"sqlite:///{sqlite_path(self.store_url).resolve()}"
        return self.store_url

    @property
    def uploads_dir(self) -> Path:
        """Uploads being received, in one folder per process (removed when the process stops)."""
        return self.data_dir / "uploads"

    @property
    def jobs_dir(self) -> Path:
        """Uploads kept for their jobs until they finish, so an interrupted job can be retried."""
        return self.data_dir / "jobs"
