"""All configuration, from environment variables prefixed ``CKS_`` (README, Configuration).

Settings come in groups (``settings.predict.max_request_bytes``); each field is still the one
variable ``CKS_<FIELD>``, and ``Settings(max_request_bytes=...)`` takes any field by its name.
``python -m service.infra.settings`` writes the README's table from the fields.
"""

from __future__ import annotations

import ipaddress
import json
import re
import sys
from collections.abc import Mapping
from functools import cached_property
from pathlib import Path
from typing import Annotated, Any, Literal

from pydantic import AfterValidator, BaseModel, ConfigDict, Field, ValidationError, field_validator
from pydantic.fields import FieldInfo
from pydantic_settings import BaseSettings, NoDecode, SettingsConfigDict

from calibration_store import sqlite_path

PACKAGE_ROOT = Path(__file__).resolve().parents[2]
DEFAULT_MODEL_DIR = PACKAGE_ROOT / "models" / "lmo-synth-unet"
README = PACKAGE_ROOT / "README.md"

_ONE_RUN = (
    "micro-batching was removed; each request's crops are one run on its own thread, with"
    " CKS_INFERENCE_THREADS intra-op threads"
)
_PROXY = "the proxy in front of the service does this (deploy/haproxy/haproxy.cfg, docs/deploy.md)"
_CALLER = (
    "a caller is its predict token (a 'predict name:token' line of CKS_ADMIN_TOKENS_FILE) or its address,"
    " and each caller's share is CKS_CLIENT_SHARE; shares by network are the proxy's (deploy/haproxy)"
)
_FIXED = "fixed at {}"
#: Settings no longer read: what replaced each. One that is still set stops the start-up.
REMOVED_SETTINGS = {
    "CKS_MAX_INFERENCE_BATCH": _ONE_RUN,
    "CKS_INFERENCE_STREAMS": _ONE_RUN,
    "CKS_BATCH_WINDOW_MS": _ONE_RUN,
    "CKS_SOLO_INFERENCE_THREADS": "a request alone in a process always runs on every usable core, and one"
    " beside others with CKS_INFERENCE_THREADS intra-op threads",
    "CKS_KEEP_CORES_AWAKE": "removed with its mechanism: onnxruntime's own threads run a lone request",
    "CKS_CPU_WORKERS": "the threads for decode, crop and scoring are CKS_MAX_CONCURRENT_INFERENCES",
    "CKS_STORE_POLL_SECONDS": _FIXED.format("1 s"),
    "CKS_STORE_TIMEOUT_SECONDS": _FIXED.format("1.5 s"),
    "CKS_MAX_CACHE_STALENESS_SECONDS": "/readyz reports the store's state in its body; predictions go on"
    " from memory while the store is away",
    "CKS_MAX_CONNECTIONS": _PROXY + " (maxconn)",
    "CKS_HEADER_READ_TIMEOUT_SECONDS": _PROXY + " (timeout http-request)",
    "CKS_MIN_BODY_BYTES_PER_SECOND": _PROXY + " (timeout http-request)",
    "CKS_BODY_RATE_GRACE_SECONDS": _PROXY + " (timeout http-request)",
    "CKS_MAX_BATCH_IMAGES": _FIXED.format("16 images per batch"),
    "CKS_REQUEST_READ_TIMEOUT_SECONDS": _FIXED.format("30 s") + "; cutting slow clients sooner: " + _PROXY,
    "CKS_MAX_RECEIVING_BYTES": _PROXY + ": it buffers request bodies (option http-buffer-request)",
    "CKS_MAX_DECODED_BYTES": _FIXED.format("256 MiB of decoded pixels per image"),
    "CKS_QUEUE_TIMEOUT_SECONDS": _FIXED.format("10 s"),
    "CKS_CLIENT_HEADER": "X-Forwarded-For from CKS_TRUSTED_PROXIES names the caller",
    "CKS_CLIENT_IPV4_PREFIX": _CALLER,
    "CKS_CLIENT_IPV6_PREFIX": _CALLER,
    "CKS_CLIENT_NETWORK_IPV4_PREFIX": _CALLER,
    "CKS_CLIENT_NETWORK_IPV6_PREFIX": _CALLER,
    "CKS_MAX_UPLOAD_FILES": _FIXED.format("100,000 files"),
    "CKS_MAX_UPLOAD_UNCOMPRESSED_BYTES": _FIXED.format("4 GiB"),
    "CKS_MAX_ANNOTATIONS_BYTES": _FIXED.format("16 MiB"),
    "CKS_MAX_ANNOTATIONS": _FIXED.format("20,000"),
    "CKS_UPLOAD_READ_TIMEOUT_SECONDS": _FIXED.format("1 h"),
    "CKS_MIN_FREE_DISK_BYTES": _FIXED.format("1 GiB, or a twentieth of a smaller file system"),
    "CKS_STRATUM_SIGNALS": _FIXED.format("gamma,peak_probability"),
    "CKS_STRATUM_BINS": _FIXED.format("3"),
    "CKS_MIN_STRATUM_INSTANCES": _FIXED.format("30"),
    "CKS_MAX_REJECTED_SHARE": "an upload's max_rejected_share query option (default 0)",
    "CKS_DRIFT_PSI_THRESHOLD": _FIXED.format("0.25"),
    "CKS_DRIFT_FULL_STATISTICS_SHARE": _FIXED.format("0.25"),
    "CKS_DRIFT_HISTORY_SECONDS": _FIXED.format("60 s"),
    "CKS_MAX_INSTANCES": _FIXED.format("64 instances per image"),
    "CKS_FEEDBACK_ACI_GAMMA": _FIXED.format("0.005"),
}


class RemovedSettings(ValueError):
    """Settings still set that are no longer read; the message says what replaced each."""


def refuse_removed_settings(environ: Mapping[str, str]) -> None:
    """Stop the start-up while ``environ`` sets a removed setting: its value would be ignored silently."""
    lines = [f"{name} is no longer read: {why}" for name, why in REMOVED_SETTINGS.items() if name in environ]
    if lines:
        raise RemovedSettings("; ".join(lines) + ". Unset " + ("it." if len(lines) == 1 else "them."))


def _absolute(path: Path) -> Path:
    """Resolved once, against the directory the service starts in, and said at start-up."""
    return path.expanduser().resolve()


AbsolutePath = Annotated[Path, AfterValidator(_absolute)]


class _Group(BaseSettings):
    """One group of settings, each read from its variable: ``CKS_`` + the group's prefix + the field's
    name in capitals, or the field's own ``validation_alias`` where the variable is older than the group."""

    model_config = SettingsConfigDict(env_prefix="CKS_", extra="ignore", frozen=True, validate_by_name=True)

    @classmethod
    def variables(cls) -> dict[str, str]:
        """Each setting's name (its variable without ``CKS_``, in lower case) -> the field holding it."""
        prefix = cls.model_config.get("env_prefix", "CKS_").removeprefix("CKS_").lower()
        return {
            alias.removeprefix("CKS_").lower()
            if isinstance(alias := field.validation_alias, str)
            else prefix + name: name
            for name, field in cls.model_fields.items()
        }


class ModelSettings(_Group):
    """The model and how it runs: where it is, onnxruntime's providers and threads."""

    directory: AbsolutePath = Field(
        default=DEFAULT_MODEL_DIR,
        validation_alias="CKS_MODEL_DIR",
        description="directory with model.onnx and manifest.json",
    )
    execution_providers: Annotated[tuple[str, ...], NoDecode] = Field(
        default=("CPUExecutionProvider",),
        description=(
            "onnxruntime execution providers in order of preference, comma-separated or a JSON list (e.g."
            " `CUDAExecutionProvider,CPUExecutionProvider`; GPU install: docs/operations.md, Execution "
            "providers and GPUs); one this onnxruntime lacks is refused at start-up (exit 2), and `GET "
            "/v1/model` reports those in use"
        ),
    )
    execution_provider_options: dict[str, dict[str, str]] = Field(
        default_factory=dict,
        description=(
            'JSON options per provider, e.g. `{"CUDAExecutionProvider": {"device_id": "1"}}`, over the '
            "service's own: CUDA runs with `use_tf32=0` and `cudnn_conv_algo_search=HEURISTIC` unless "
            "told otherwise (TF32 makes the sets depend on the batch; docs/operations.md)"
        ),
    )
    inference_threads: int = Field(
        default=1,
        ge=0,
        description=(
            "onnxruntime intra-op threads of a run while other requests compute in the same process "
            "(0 = onnxruntime's default for every run); a request alone in the process runs on every "
            "usable core (its CPU affinity and cgroup quota). Raise it on a many-core machine whose load"
            " is a few clients at a time"
        ),
    )

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


class StorageSettings(_Group):
    """Where the service writes, and the calibration store."""

    data_dir: AbsolutePath = Field(
        default=Path("var"),
        description="where the service writes (SQLite store, uploads, metrics files of several workers)",
    )
    url: str | None = Field(
        default=None,
        validation_alias="CKS_STORE_URL",
        description="sqlite:///path or postgresql://...; default sqlite under data_dir",
    )
    bootstrap_calibration: bool = Field(
        default=True, description="load the model's bundled calibration as version 1 when the store has none"
    )

    @field_validator("url")
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

    @cached_property
    def resolved_url(self) -> str:
        if not self.url:
            return f"sqlite:///{self.data_dir / 'calibrations.db'}"
        if self.url.startswith("sqlite:") and not self.url.startswith("sqlite:///"):
            return f"sqlite:///{sqlite_path(self.url).resolve()}"
        return self.url

    @property
    def uploads_dir(self) -> Path:
        """Uploads being received, in one folder per process (removed when the process stops)."""
        return self.data_dir / "uploads"

    @property
    def jobs_dir(self) -> Path:
        """Uploads kept for their jobs until they finish, so an interrupted job can be retried."""
        return self.data_dir / "jobs"


class AdminSettings(_Group):
    """Who may use the admin API."""

    model_config = SettingsConfigDict(env_prefix="CKS_ADMIN_")

    token: str | None = Field(
        default=None,
        description=(
            "bearer token for /v1/admin (operator 'admin'): 16+ characters without spaces, like every "
            "token; unset disables it"
        ),
    )
    tokens_file: AbsolutePath | None = Field(
        default=None,
        description=(
            "file of 'name:token' lines (tokens as above): named admin operators for the audit trail;"
            " 'feedback name:token' lines may only send feedback; 'predict name:token' lines turn predict"
            " tokens on: predict then needs a predict or admin token, and each holder is one caller"
        ),
    )


class ServerSettings(_Group):
    """The HTTP server: address, processes, shutdown."""

    host: str = Field(default="127.0.0.1", description="address to listen on")
    port: int = Field(default=8000, ge=1, le=65535, description="port to listen on")
    workers: int = Field(
        default=1,
        ge=1,
        le=64,
        description=(
            "uvicorn worker processes (the predict limits below are per process); jobs and `/metrics`"
            " cover all of them. Raise it when many clients at once keep one process's interpreter busy"
            " (docs/performance.md); on a GPU, about half the cores"
        ),
    )
    shutdown_grace_seconds: float = Field(
        default=20.0,
        ge=0,
        description=(
            "on SIGTERM, longest wait for in-flight requests before running jobs are interrupted (see "
            "Deployment)"
        ),
    )


class PredictSettings(_Group):
    """Predict requests: body, image and instance limits, admission."""

    max_request_bytes: int = Field(default=20 * 2**20, gt=0, description="largest predict request body")
    max_image_pixels: int = Field(default=40_000_000, gt=0, description="largest width*height decoded")
    max_concurrent_inferences: int = Field(
        default=8,
        gt=0,
        description="predict requests computing at once (and the threads that decode, crop and score them)",
    )
    max_queued_requests: int = Field(
        default=32, ge=0, description="predict requests waiting for a slot; more get 503 at once"
    )
    client_share: float = Field(
        default=0.5,
        gt=0,
        le=1,
        description=(
            "share of the predict places (and of the compute threads that run at once) one caller may hold"
            " while other callers have asked in the last 30 s: beyond, a request waits, its body unread, up"
            " to 10 s for one of its caller's places, then `429` with `Retry-After`; a caller alone may use"
            " them all. A caller is its predict token, else its address. 1 = no cap per caller"
        ),
    )
    trusted_proxies: Annotated[tuple[str, ...], NoDecode] = Field(
        default=(),
        description=(
            "addresses or networks (comma-separated) of the proxies in front of the service, whose"
            " `X-Forwarded-For` names the caller; set it to the proxy's address behind deploy/haproxy"
        ),
    )

    @field_validator("trusted_proxies", mode="before")
    @classmethod
    def _networks(cls, proxies: object) -> object:
        if isinstance(proxies, str):
            proxies = [proxy.strip() for proxy in proxies.split(",") if proxy.strip()]
        for proxy in proxies if isinstance(proxies, list | tuple) else ():
            try:
                ipaddress.ip_network(proxy, strict=False)
            except ValueError as error:
                raise ValueError(f"{error}: give addresses or networks such as 10.0.0.0/8") from None
        return proxies


class CalibrationSettings(_Group):
    """Calibration uploads and jobs: limits and the activation floor."""

    max_upload_bytes: int = Field(default=2 * 2**30, gt=0, description="largest calibration zip")
    max_uploads_disk_bytes: int = Field(
        default=16 * 2**30,
        gt=0,
        description="disk kept uploads (zips, unzipped batches of unfinished jobs) may take (507 beyond)",
    )
    workers: int = Field(
        default=1,
        gt=0,
        validation_alias="CKS_CALIBRATION_WORKERS",
        description="calibration jobs running at once",
    )
    min_instances: int = Field(
        validation_alias="CKS_MIN_CALIBRATION_INSTANCES",
        default=100,
        ge=0,
        description="activation needs this n per keypoint (unless forced with a reason)",
    )


class DriftMonitorSettings(_Group):
    """The label-free drift monitor."""

    model_config = SettingsConfigDict(env_prefix="CKS_DRIFT_")

    enabled: bool = Field(
        default=True,
        description="keep windows of every keypoint's live heatmap features and test them against the"
        " active calibration's (GET /v1/admin/drift, cks_drift_* metrics)",
    )
    window: int = Field(
        default=500,
        ge=10,
        le=100_000,
        description="live instances kept per keypoint (the drift window; each feature's window holds"
        " those that computed it)",
    )
    test: Literal["sequential", "ks", "psi"] = Field(
        default="sequential",
        description="drift test: `sequential` (one vote per independent look, an e-CUSUM over the looks:"
        " right on camera streams), `ks` (Kolmogorov-Smirnov p-values over every frame, Holm-corrected) or"
        " `psi` (population stability index over 10 quantile bins)",
    )
    alarm_level: float = Field(
        default=0.01,
        gt=0,
        lt=1,
        description="sequential: on a stream like the calibration, at least 1 / this independent looks"
        " between false alarms on average; ks: family-wise error rate of one evaluation over all keypoints x"
        " features (Holm)",
    )
    share_seconds: float = Field(
        default=5.0,
        gt=0,
        description=(
            "how often each process writes its drift windows and looks to the store, where any worker or"
            " replica merges them to answer for the fleet (GET /v1/admin/drift, cks_drift_*); a restart"
            " loses at most this much. Raise it for a fleet of many replicas: each writes its windows"
            " this often"
        ),
    )


class FeedbackSettings(_Group):
    """Feedback on served predictions: retention, live labelled coverage, adaptive sets."""

    model_config = SettingsConfigDict(env_prefix="CKS_FEEDBACK_")

    retain_share: float = Field(
        default=0.0,
        ge=0,
        le=1,
        description="share of predict answers retained for feedback without asking (`retain: true` always"
        " retains); a retained answer carries a prediction_id",
    )
    max_age_seconds: float = Field(
        default=7 * 24 * 3600.0,
        gt=0,
        description="how long a retained prediction waits for its feedback (then 410)",
    )
    max_retained: int = Field(
        default=100_000,
        ge=1,
        description="retained predictions kept in the store, labelled or not; the oldest go first (then 410)",
    )
    alarm_level: float = Field(
        default=0.01,
        gt=0,
        lt=0.5,
        description="live coverage: probability of a false coverage alarm per group, however long it is"
        " watched (the alarm's ladder of floors over the calibration's Beta law, docs/feedback.md; exact"
        " for a group of one threshold, at most K times it for a group of K thresholds whose coverages"
        " do not move together), and of the confidence sequence missing the mean",
    )


class LogSettings(_Group):
    """Logging."""

    model_config = SettingsConfigDict(env_prefix="CKS_LOG_")

    format: Literal["text", "json"] = Field(
        default="text",
        description="`text` (one line: UTC time, level, logger, [request id], message) or `json`"
        " (one JSON object a line), for the service's lines and uvicorn's alike",
    )
    level: Literal["DEBUG", "INFO", "WARNING", "ERROR"] = Field(
        default="INFO",
        description="least severe level logged by `serve`; the other commands log warnings and errors"
        " only unless it is set",
    )
    access_log: bool = Field(
        validation_alias="CKS_ACCESS_LOG",
        default=True,
        description="one line per request: method, path, status, latency, request id, calibration version",
    )

    @field_validator("level", mode="before")
    @classmethod
    def _upper(cls, level: object) -> object:
        return level.upper() if isinstance(level, str) else level


class Settings(BaseModel):
    """Every setting of the service, by group."""

    model_config = ConfigDict(frozen=True)

    model: ModelSettings
    storage: StorageSettings
    admin: AdminSettings
    server: ServerSettings
    predict: PredictSettings
    calibration: CalibrationSettings
    drift: DriftMonitorSettings
    feedback: FeedbackSettings
    logs: LogSettings

    def __init__(self, **values: Any) -> None:
        """Any setting by its name, the variable's without ``CKS_`` (``data_dir=...``, ``drift_window=...``);
        the others from the environment."""
        unknown = set(values) - set(Settings.fields())
        if unknown:
            raise TypeError(f"not settings: {', '.join(sorted(unknown))}")
        groups, problems = {}, []
        for name, group in _GROUPS.items():
            variables = group.variables()
            try:
                groups[name] = group(
                    **{variables[key]: value for key, value in values.items() if key in variables}
                )
            except ValidationError as error:  # every group's problems are told at once, by setting name
                setting = {field: key for key, field in variables.items()}
                setting |= {
                    f.validation_alias: key for key, f in _fields_of(group).items() if f.validation_alias
                }
                problems += [
                    {key: e[key] for key in ("type", "loc", "input", "ctx") if key in e}
                    | {"loc": (setting.get(e["loc"][0], e["loc"][0]), *e["loc"][1:])}
                    for e in error.errors()
                ]
        if problems:
            raise ValidationError.from_exception_data("Settings", problems)
        super().__init__(**groups)

    def value(self, name: str) -> Any:
        """A setting by its name (the variable's without ``CKS_``), whatever its group."""
        for attribute, group in _GROUPS.items():
            if field := group.variables().get(name):
                return getattr(getattr(self, attribute), field)
        raise KeyError(name)

    @classmethod
    def fields(cls) -> dict[str, FieldInfo]:
        """Every setting's field, by name (the variable is ``CKS_`` + the name in capitals)."""
        return {name: field for group in _GROUPS.values() for name, field in _fields_of(group).items()}


def _fields_of(group: type[_Group]) -> dict[str, FieldInfo]:
    """A group's fields by setting name."""
    return {name: group.model_fields[field] for name, field in group.variables().items()}


_GROUPS: dict[str, type[_Group]] = {
    name: field.annotation
    for name, field in Settings.model_fields.items()  # type: ignore[misc]
}


_SHOWN_DEFAULTS = {"model_dir": "models/lmo-synth-unet (bundled)", "store_url": "sqlite under CKS_DATA_DIR"}
_TABLE = re.compile(
    r"(<!-- settings table: python -m service.infra.settings -->\n).*?(\n<!-- end of settings -->)", re.S
)


def settings_table() -> str:
    """The README's Configuration table: a section per group, a row per setting."""
    lines = []
    for group in _GROUPS.values():
        lines += [f"**{group.__doc__}**", "", "| variable | default | meaning |", "|---|---|---|"]
        for name, field in _fields_of(group).items():
            default = _SHOWN_DEFAULTS.get(name, field.get_default(call_default_factory=True))
            if isinstance(default, tuple):
                default = ",".join(default)
            lines.append(f"| `CKS_{name.upper()}` | `{default}` | {field.description} |")
        lines.append("")
    return "\n".join(lines).rstrip("\n")


def readme_with_table(readme: str) -> str:
    """``readme`` with its settings table made anew from the fields."""
    if not _TABLE.search(readme):
        raise ValueError("README.md has no settings table markers")
    return _TABLE.sub(lambda match: match.group(1) + settings_table() + match.group(2), readme)


if __name__ == "__main__":
    README.write_text(readme_with_table(README.read_text(encoding="utf-8")), encoding="utf-8")
    print(f"{README}: settings table written ({len(Settings.fields())} settings)", file=sys.stderr)
