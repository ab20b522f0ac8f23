"""What the client raises: the service's RFC 9457 problems as typed exceptions, and its own failures."""

from __future__ import annotations

from typing import TYPE_CHECKING, Any

from keypoint_client.generated_models import Problem
from keypoint_client.models import Comparison

if TYPE_CHECKING:
    from keypoint_client.models import Job

PROBLEM_MEMBERS = frozenset(Problem.model_fields)


class KeypointClientError(Exception):
    """Base of every error this client raises."""


class ProblemError(KeypointClientError):
    """The service answered with an error status; ``detail`` says what to fix, ``errors`` lists
    every problem found, ``request_id`` names the request in the service's logs."""

    def __init__(
        self,
        status: int,
        title: str,
        detail: str,
        *,
        errors: list[str] | None = None,
        request_id: str | None = None,
        retry_after: float | None = None,
        body: dict[str, Any] | None = None,
    ) -> None:
        super().__init__(f"{status} {title}: {detail}" + (f" (request {request_id})" if request_id else ""))
        self.status, self.title, self.detail = status, title, detail
        self.errors = errors or []
        self.request_id = request_id
        self.retry_after = retry_after
        self.body = body or {}

    @property
    def extensions(self) -> dict[str, Any]:
        """The problem's members beyond RFC 9457's and ``errors``/``request_id`` (e.g. ``comparison``)."""
        return {key: value for key, value in self.body.items() if key not in PROBLEM_MEMBERS}


class BadRequest(ProblemError):
    """400"""


class Unauthorized(ProblemError):
    """401: no admin token, or a wrong one."""


class Forbidden(ProblemError):
    """403: the admin API is disabled on this server."""


class NotFound(ProblemError):
    """404"""


class RequestTimeout(ProblemError):
    """408: the body arrived too slowly."""


class Conflict(ProblemError):
    """409"""


class ActivationRefused(Conflict):
    """409 from the activation guardrails; ``comparison`` says which keypoints fall short."""

    def __init__(
        self, status: int, title: str, detail: str, *, comparison: Comparison, **kwargs: Any
    ) -> None:
        super().__init__(status, title, detail, **kwargs)
        self.comparison = comparison


class PayloadTooLarge(ProblemError):
    """413"""


class UnsupportedMediaType(ProblemError):
    """415"""


class InvalidInput(ProblemError):
    """422: the request is invalid; ``errors`` lists every problem."""


class TooManyRequests(ProblemError):
    """429: this client holds its share of the service while others are served; ``retry_after``
    is the server's advice in seconds (the service did not act)."""


class ServerError(ProblemError):
    """5xx other than 503."""


class ServiceUnavailable(ServerError):
    """503: overloaded or its store is away; ``retry_after`` is the server's advice in seconds."""


class InsufficientStorage(ServerError):
    """507: the service's disk is full; nothing of the request was kept."""


_BY_STATUS: dict[int, type[ProblemError]] = {
    400: BadRequest,
    401: Unauthorized,
    403: Forbidden,
    404: NotFound,
    408: RequestTimeout,
    409: Conflict,
    413: PayloadTooLarge,
    415: UnsupportedMediaType,
    422: InvalidInput,
    429: TooManyRequests,
    503: ServiceUnavailable,
    507: InsufficientStorage,
}


def problem_error(
    status: int, body: dict[str, Any], request_id: str | None, retry_after: float | None = None
) -> ProblemError:
    """The exception for a problem body (or for what stood in for one)."""
    title, detail = str(body.get("title", "Error")), str(body.get("detail", ""))
    errors = [str(error) for error in body.get("errors") or []]
    request_id = str(body.get("request_id") or request_id or "") or None
    kwargs: dict[str, Any] = {"errors": errors, "request_id": request_id, "retry_after": retry_after}
    kwargs["body"] = body
    if status == 409 and isinstance(body.get("comparison"), dict):
        comparison = Comparison.model_validate(body["comparison"])
        return ActivationRefused(status, title, detail, comparison=comparison, **kwargs)
    kind = _BY_STATUS.get(status, ServerError if status >= 500 else ProblemError)
    return kind(status, title, detail, **kwargs)


class ConnectionFailed(KeypointClientError):
    """The service could not be reached, or the connection broke, on every attempt allowed."""


class JobFailed(KeypointClientError):
    """A calibration job ended failed or interrupted; ``job.errors`` says why."""

    def __init__(self, job: Job) -> None:
        why = "; ".join(job.errors[:5]) or "no reason given"
        super().__init__(f"calibration job {job.id} {job.state}: {why}")
        self.job = job


class JobWaitTimeout(KeypointClientError, TimeoutError):
    """A calibration job was still unfinished when the wait's timeout ran out; ``job`` is its last state."""

    def __init__(self, job: Job, timeout: float) -> None:
        where = f"{job.state} ({job.done}/{job.total} instances)"
        super().__init__(f"calibration job {job.id} still {where} after {timeout:g} s")
        self.job = job
