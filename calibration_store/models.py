"""Value objects of the calibration store, validated on construction.

Invalid input raises ValueError (or TypeError for a wrong type) with a message that
says what to fix; a constructed object is always storable.
"""

from __future__ import annotations

import json
import re
from collections.abc import Iterable, Mapping, Sequence
from dataclasses import dataclass, field
from datetime import datetime
from typing import Any

import numpy as np

#: Nonconformity functions the service computes; the store accepts any lowercase name.
DEFAULT_FUNCTIONS: tuple[str, ...] = ("peak", "var", "cov")

_FUNCTION_RE = re.compile(r"^[a-z][a-z0-9_]{0,62}$")
_SHA256_RE = re.compile(r"^[0-9a-f]{64}$")


def _text(value: object, what: str, *, allow_empty: bool = False) -> str:
    if not isinstance(value, str):
        raise TypeError(f"{what} must be a string, got {type(value).__name__}")
    if not allow_empty and not value.strip():
        raise ValueError(f"{what} must be a non-empty string")
    return value


def _count(value: object, what: str, *, minimum: int = 0) -> int:
    if isinstance(value, bool) or not isinstance(value, int | np.integer):
        raise TypeError(f"{what} must be an integer, got {type(value).__name__}")
    if value < minimum:
        raise ValueError(f"{what} must be >= {minimum}, got {value}")
    return int(value)


@dataclass(frozen=True)
class SourceBatch:
    """One uploaded labeled batch a version was computed from."""

    name: str
    sha256: str
    instances: int

    def __post_init__(self) -> None:
        _text(self.name, "source batch name")
        digest = _text(self.sha256, f"sha256 of batch {self.name!r}").lower()
        if not _SHA256_RE.match(digest):
            raise ValueError(f"sha256 of batch {self.name!r} must be 64 hex digits")
        object.__setattr__(self, "sha256", digest)
        object.__setattr__(self, "instances", _count(self.instances, f"instances of batch {self.name!r}"))

    @classmethod
    def coerce(cls, value: SourceBatch | Mapping[str, Any]) -> SourceBatch:
        """Accept a SourceBatch or a mapping with keys name, sha256, instances."""
        if isinstance(value, SourceBatch):
            return value
        if not isinstance(value, Mapping):
            raise TypeError("a source batch must be a SourceBatch or a mapping")
        missing = {"name", "sha256", "instances"} - set(value)
        if missing:
            raise ValueError(f"source batch is missing {sorted(missing)}")
        return cls(name=value["name"], sha256=value["sha256"], instances=value["instances"])

    def as_dict(self) -> dict[str, Any]:
        return {"name": self.name, "sha256": self.sha256, "instances": self.instances}


def _float_matrix(values: object, what: str, shape: tuple[int, int]) -> np.ndarray:
    array = np.asarray(values)
    if array.dtype.kind not in "fiu":
        raise ValueError(f"{what} must hold real numbers, got dtype {array.dtype}")
    array = np.ascontiguousarray(array, dtype=np.float64)
    if array.shape != shape:
        raise ValueError(f"{what} must have shape {shape} (instances, keypoints), got {array.shape}")
    if np.isinf(array).any():
        raise ValueError(f"{what} contains infinite values (use NaN for unlabeled keypoints)")
    return array


def _digests(values: object, what: str, count: int) -> tuple[str, ...]:
    """Empty, or exactly ``count`` lowercase sha256 hex digests."""
    if isinstance(values, str | bytes) or not isinstance(values, Iterable):
        raise TypeError(f"{what} must be a sequence of sha256 hex digests")
    digests = tuple(values)
    if digests and len(digests) != count:
        raise ValueError(f"{what} has {len(digests)} digests for {count} instances")
    for digest in digests:
        if not isinstance(digest, str) or not _SHA256_RE.match(digest):
            raise ValueError(f"{what} must hold 64 lowercase hex digits each, got {digest!r}")
    return digests


def _keypoint_ids(values: object, what: str) -> np.ndarray:
    array = np.asarray(values)
    if array.ndim != 1 or array.size == 0:
        raise ValueError(f"{what} must be a non-empty 1-D array of keypoint indices")
    if array.dtype.kind not in "iu":
        raise ValueError(f"{what} must hold integers, got dtype {array.dtype}")
    array = np.ascontiguousarray(array, dtype=np.int64)
    if (array < 0).any():
        raise ValueError(f"{what} must be non-negative")
    if np.unique(array).size != array.size:
        raise ValueError(f"{what} contains duplicates")
    return array


def _features(values: object, name: str, shape: tuple[int, int]) -> dict[str, np.ndarray]:
    if not isinstance(values, Mapping):
        raise TypeError(f"features of {name!r} must map feature names to matrices")
    matrices = {}
    for feature, matrix in values.items():
        if not isinstance(feature, str) or not _FUNCTION_RE.match(feature):
            raise ValueError(f"feature name {feature!r} must match {_FUNCTION_RE.pattern}")
        array = _float_matrix(matrix, f"feature {feature} of {name!r}", shape)
        if np.isnan(array).any():
            raise ValueError(f"feature {feature} of {name!r} must be finite for every keypoint")
        matrices[feature] = array
    return matrices


_GROUP_RE = re.compile(r"^[\x20-\x7e]{0,64}$")


def _groups(values: object, name: str, count: int) -> tuple[str, ...]:
    """Empty, or exactly ``count`` printable ASCII labels of at most 64 characters ("" = none)."""
    if isinstance(values, str | bytes) or not isinstance(values, Iterable):
        raise TypeError(f"groups of {name!r} must be a sequence of strings")
    groups = tuple(values)
    if groups and len(groups) != count:
        raise ValueError(f"groups of {name!r} has {len(groups)} labels for {count} instances")
    for group in groups:
        if not isinstance(group, str) or not _GROUP_RE.match(group):
            raise ValueError(
                f"group labels of {name!r} must be printable ASCII, at most 64 characters, got {group!r}"
            )
    return groups


@dataclass(frozen=True, eq=False)
class ObjectScores:
    """Scores of every instance of one object class.

    keypoint_ids: (k,) global manifest keypoint indices, the matrix columns in order.
    instance_refs: (n,) opaque per-instance references (e.g. "batch:image:annotation").
    scores: nonconformity function name -> (n, k) float64 matrix; NaN = not labeled.
    image_hashes, instance_hashes: (n,) sha256 hex digests of each instance's image file
    and of the instance itself (image, object, box, labels), so that a batch appended
    later can be checked for repeats; both empty when unknown (versions made without them).
    features: feature name -> (n, k) float64 label-free heatmap statistics of every
    keypoint (labeled or not, all finite): the reference distribution for drift and the
    difficulty signal of Mondrian strata; empty when unknown (versions made without them).
    groups: (n,) caller group labels ("" = none); empty when no instance carried one.
    """

    object_name: str
    keypoint_ids: np.ndarray
    instance_refs: tuple[str, ...]
    scores: Mapping[str, np.ndarray]
    image_hashes: tuple[str, ...] = ()
    instance_hashes: tuple[str, ...] = ()
    features: Mapping[str, np.ndarray] = field(default_factory=dict)
    groups: tuple[str, ...] = ()

    def __post_init__(self) -> None:
        name = _text(self.object_name, "object name")
        ids = _keypoint_ids(self.keypoint_ids, f"keypoint_ids of {name!r}")
        refs = tuple(self.instance_refs)
        for ref in refs:
            _text(ref, f"instance reference of {name!r}", allow_empty=True)
        if not refs:
            raise ValueError(f"object {name!r} has no instances")
        if not isinstance(self.scores, Mapping) or not self.scores:
            raise ValueError(f"scores of {name!r} must map function names to matrices")
        shape = (len(refs), ids.size)
        matrices = {}
        for function, values in self.scores.items():
            if not isinstance(function, str) or not _FUNCTION_RE.match(function):
                raise ValueError(f"function name {function!r} must match {_FUNCTION_RE.pattern}")
            matrices[function] = _float_matrix(values, f"{function} scores of {name!r}", shape)
        object.__setattr__(self, "keypoint_ids", ids)
        object.__setattr__(self, "instance_refs", refs)
        object.__setattr__(self, "scores", matrices)
        for what in ("image_hashes", "instance_hashes"):
            object.__setattr__(self, what, _digests(getattr(self, what), f"{what} of {name!r}", len(refs)))
        if bool(self.image_hashes) != bool(self.instance_hashes):
            raise ValueError(f"object {name!r}: give both image_hashes and instance_hashes, or neither")
        object.__setattr__(self, "features", _features(self.features, name, shape))
        object.__setattr__(self, "groups", _groups(self.groups, name, len(refs)))

    @property
    def has_features(self) -> bool:
        return bool(self.features)

    @property
    def has_groups(self) -> bool:
        return bool(self.groups)

    @property
    def has_hashes(self) -> bool:
        return bool(self.instance_hashes)

    @property
    def n_instances(self) -> int:
        return len(self.instance_refs)

    @property
    def functions(self) -> tuple[str, ...]:
        return tuple(sorted(self.scores))


@dataclass(frozen=True, eq=False)
class ScoreTable:
    """All per-instance scores of one calibration version, one block per object class.

    Every block carries the same set of nonconformity functions.
    """

    objects: tuple[ObjectScores, ...]

    def __post_init__(self) -> None:
        blocks = tuple(self.objects)
        if not blocks:
            raise ValueError("a score table needs at least one object block")
        for block in blocks:
            if not isinstance(block, ObjectScores):
                raise TypeError("score table objects must be ObjectScores")
        names = [block.object_name for block in blocks]
        if len(set(names)) != len(names):
            raise ValueError(f"object names must be unique, got {names}")
        functions = {block.functions for block in blocks}
        if len(functions) != 1:
            raise ValueError(f"every object must carry the same functions, got {sorted(functions)}")
        object.__setattr__(self, "objects", blocks)

    @property
    def functions(self) -> tuple[str, ...]:
        return self.objects[0].functions

    @property
    def n_instances(self) -> int:
        return sum(block.n_instances for block in self.objects)

    def object(self, name: str) -> ObjectScores:
        """The block of one object class (KeyError if absent)."""
        for block in self.objects:
            if block.object_name == name:
                return block
        raise KeyError(name)

    def object_counts(self) -> dict[str, int]:
        return {block.object_name: block.n_instances for block in self.objects}


def _json_object(value: object, what: str) -> dict[str, Any]:
    if not isinstance(value, Mapping):
        raise TypeError(f"{what} must be a mapping")
    try:
        return json.loads(json.dumps(dict(value), allow_nan=False, sort_keys=True))
    except (TypeError, ValueError) as exc:
        raise ValueError(f"{what} must be plain JSON: {exc}") from exc


def _normalization(value: object) -> dict[str, Any]:
    return _json_object(value, "normalization settings")


@dataclass(frozen=True)
class NewVersion:
    """Metadata of a version to create; the store sets number and created_at."""

    model_hash: str
    model_name: str
    normalization: Mapping[str, Any]
    source_batches: Sequence[SourceBatch | Mapping[str, Any]]
    author: str
    note: str = ""
    parent_version: int | None = None
    strata: Mapping[str, Any] | None = None  # Mondrian strata: spec and edges (JSON), None = none
    #: a sha256 hex digest of what the version is: at most one version per model has it (None: no rule)
    content_key: str | None = None

    def __post_init__(self) -> None:
        _text(self.model_hash, "model hash")
        key = self.content_key
        if key is not None and not (isinstance(key, str) and _SHA256_RE.match(key)):
            raise ValueError("content key must be a sha256 hex digest (64 lowercase hex characters)")
        if self.model_hash != self.model_hash.strip():
            raise ValueError("model hash must not have surrounding whitespace")
        _text(self.model_name, "model name")
        _text(self.author, "author")
        _text(self.note, "note", allow_empty=True)
        if self.parent_version is not None:
            _count(self.parent_version, "parent version", minimum=1)
        batches = tuple(SourceBatch.coerce(b) for b in _iterable(self.source_batches))
        object.__setattr__(self, "source_batches", batches)
        object.__setattr__(self, "normalization", _normalization(self.normalization))
        if self.strata is not None:
            object.__setattr__(self, "strata", _json_object(self.strata, "strata"))


def _iterable(value: object) -> Iterable[Any]:
    if isinstance(value, str | bytes | Mapping) or not isinstance(value, Iterable):
        raise TypeError("source batches must be a list")
    return value


@dataclass(frozen=True)
class VersionInfo:
    """Metadata of a stored, immutable calibration version."""

    model_hash: str
    number: int
    model_name: str
    normalization: Mapping[str, Any]
    source_batches: tuple[SourceBatch, ...]
    author: str
    note: str
    parent_version: int | None
    created_at: datetime
    n_instances: int
    object_counts: Mapping[str, int] = field(default_factory=dict)
    functions: tuple[str, ...] = ()
    strata: Mapping[str, Any] | None = None


@dataclass(frozen=True)
class Activation:
    """One entry of the append-only activation log (seq orders entries store-wide)."""

    seq: int
    model_hash: str
    version: int
    activated_at: datetime
    who: str
    reason: str


#: States of a background job; the last three are final. ``interrupted``: its process
#: stopped before it finished (nothing was stored); it may be retried as a new job.
JOB_STATES: tuple[str, ...] = ("queued", "running", "succeeded", "failed", "interrupted")
FINAL_JOB_STATES: tuple[str, ...] = ("succeeded", "failed", "interrupted")
MAX_JOB_ID = 200

#: JobRecord fields update_job may change (the rest are set once by create_job).
JOB_MUTABLE_FIELDS: tuple[str, ...] = (
    "state",
    "done",
    "total",
    "errors",
    "result",
    "finished_at",
    "version",
    "heartbeat_at",
)


def _aware(value: object, what: str) -> datetime:
    if not isinstance(value, datetime):
        raise TypeError(f"{what} must be a datetime, got {type(value).__name__}")
    if value.tzinfo is None or value.utcoffset() is None:
        raise ValueError(f"{what} must be timezone-aware (e.g. datetime.now(UTC))")
    return value


def _messages(value: object, what: str) -> tuple[str, ...]:
    if isinstance(value, str | bytes) or not isinstance(value, Iterable):
        raise TypeError(f"{what} must be a list of strings")
    return tuple(_text(item, f"each of {what}", allow_empty=True) for item in value)


def is_job_id(value: object) -> bool:
    """Whether a job could be stored under this id (1 to MAX_JOB_ID printable characters)."""
    return isinstance(value, str) and 0 < len(value) <= MAX_JOB_ID and value.isprintable()


def check_job_field(name: str, value: object) -> Any:
    """Validate one mutable job field (see JOB_MUTABLE_FIELDS); returns the normalized value."""
    if name == "state":
        if value not in JOB_STATES:
            raise ValueError(f"job state must be one of {JOB_STATES}, got {value!r}")
        return value
    if name in ("done", "total"):
        return _count(value, f"job {name}")
    if name == "errors":
        return _messages(value, "job errors")
    if name == "result":
        return _json_object(value, "job result")
    if name == "finished_at":
        return None if value is None else _aware(value, "job finished_at")
    if name == "version":
        return None if value is None else _count(value, "job version", minimum=1)
    if name == "heartbeat_at":
        return _aware(value, "job heartbeat_at")
    raise ValueError(f"job field {name!r} cannot be changed; changeable: {JOB_MUTABLE_FIELDS}")


@dataclass(frozen=True)
class JobRecord:
    """One background job as stored, so that every process of every replica can report it.

    owner names the process running it (e.g. "host:pid"); heartbeat_at is refreshed by
    every write of that process, so an old heartbeat on an unfinished job means it died.
    version is the calibration version the job produced, written in the same transaction
    as the version itself.
    """

    id: str
    kind: str
    owner: str
    created_at: datetime
    heartbeat_at: datetime
    state: str = "queued"
    done: int = 0
    total: int = 0
    errors: tuple[str, ...] = ()
    result: Mapping[str, Any] = field(default_factory=dict)
    finished_at: datetime | None = None
    version: int | None = None

    def __post_init__(self) -> None:
        if not is_job_id(self.id):
            raise ValueError(f"job id must be 1 to {MAX_JOB_ID} printable characters, got {self.id!r}")
        _text(self.kind, "job kind")
        _text(self.owner, "job owner")
        _aware(self.created_at, "job created_at")
        for name in JOB_MUTABLE_FIELDS:
            object.__setattr__(self, name, check_job_field(name, getattr(self, name)))

    @property
    def finished(self) -> bool:
        return self.state in FINAL_JOB_STATES

    def progress_fields(self) -> dict[str, Any]:
        """The fields a running job changes: JOB_MUTABLE_FIELDS without heartbeat_at."""
        return {name: getattr(self, name) for name in JOB_MUTABLE_FIELDS if name != "heartbeat_at"}


@dataclass(frozen=True)
class ActivationIntent:
    """Activate the version being created, in the same transaction (who and why)."""

    who: str
    reason: str = ""

    def __post_init__(self) -> None:
        _text(self.who, "who")
        _text(self.reason, "reason", allow_empty=True)


@dataclass(frozen=True)
class JobCompletion:
    """Mark a job succeeded with this result in the transaction that creates its version.

    The store adds ``"version": <number>`` to the result and sets the job's version, so a
    version and the job that produced it are never seen apart.
    """

    job_id: str
    result: Mapping[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        if not is_job_id(self.job_id):
            raise ValueError(f"job id must be 1 to {MAX_JOB_ID} printable characters")
        object.__setattr__(self, "result", _json_object(self.result, "job result"))


@dataclass(frozen=True)
class NewAuditEntry:
    """One administrative action to append to the audit trail (the store sets seq and at).

    ``version`` None inside ``create_version`` means the version being created.
    """

    model_hash: str
    who: str
    action: str
    outcome: str
    version: int | None = None
    previous_version: int | None = None
    reason: str = ""
    client: str = ""
    details: Mapping[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        _text(self.model_hash, "model hash")
        _text(self.who, "who")
        _text(self.action, "audit action")
        _text(self.outcome, "audit outcome")
        for name in ("version", "previous_version"):
            value = getattr(self, name)
            if value is not None:
                _count(value, f"audit {name}", minimum=1)
        _text(self.reason, "reason", allow_empty=True)
        _text(self.client, "client", allow_empty=True)
        object.__setattr__(self, "details", _json_object(self.details, "audit details"))


@dataclass(frozen=True)
class AuditEntry(NewAuditEntry):
    """A stored audit entry: ``seq`` orders entries store-wide, ``at`` is when it was written."""

    seq: int = 0
    at: datetime | None = None


@dataclass(frozen=True)
class NewCoverageAudit:
    """A coverage audit of one calibration version on a labeled batch (the store sets id and
    created_at). ``report`` is the audit's plain-JSON report; the store keeps it as given."""

    model_hash: str
    version: int
    who: str
    batch_sha256: str
    n_instances: int
    report: Mapping[str, Any] = field(default_factory=dict)

    def __post_init__(self) -> None:
        _text(self.model_hash, "model hash")
        _count(self.version, "audited version", minimum=1)
        _text(self.who, "who")
        if not isinstance(self.batch_sha256, str) or not _SHA256_RE.match(self.batch_sha256):
            raise ValueError("batch sha256 must be 64 lowercase hex digits")
        _count(self.n_instances, "audited instances")
        object.__setattr__(self, "report", _json_object(self.report, "audit report"))


@dataclass(frozen=True)
class CoverageAudit(NewCoverageAudit):
    """A stored, immutable coverage audit: ``id`` orders audits store-wide."""

    id: int = 0
    created_at: datetime | None = None


def check_number(value: object, what: str = "version number") -> int:
    """Validate a version number passed to a store method."""
    return _count(value, what, minimum=1)


def check_model_hash(value: object) -> str:
    """Validate a model hash passed to a store method."""
    return _text(value, "model hash")


__all__ = [
    "DEFAULT_FUNCTIONS",
    "ActivationIntent",
    "AuditEntry",
    "CoverageAudit",
    "JobCompletion",
    "NewCoverageAudit",
    "NewAuditEntry",
    "FINAL_JOB_STATES",
    "JOB_MUTABLE_FIELDS",
    "JOB_STATES",
    "MAX_JOB_ID",
    "Activation",
    "JobRecord",
    "NewVersion",
    "ObjectScores",
    "ScoreTable",
    "SourceBatch",
    "VersionInfo",
    "check_job_field",
    "check_model_hash",
    "check_number",
    "is_job_id",
]
