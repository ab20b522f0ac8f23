"""When to try a call again, and after how long: the decisions, without any I/O.

A 503 or a 429 means the service did not act (it was overloaded, its store was away, or this
client held its share of it), so every call may be repeated after it. A connection error is
repeated only when the call is idempotent (predict, every GET), or when nothing was sent (the
connection was never made).
Each wait is exponential backoff with full jitter, and at least the server's ``Retry-After``.
"""

from __future__ import annotations

import random
import time
from dataclasses import dataclass, field
from email.utils import parsedate_to_datetime

import httpx

from keypoint_client.errors import ConnectionFailed

# Errors raised before any byte of the request left: repeating them is always safe.
_NOTHING_SENT = (httpx.ConnectError, httpx.ConnectTimeout, httpx.PoolTimeout)


@dataclass(frozen=True)
class RetryPolicy:
    """``attempts`` in all (1: never retry); the n-th retry waits up to ``backoff * 2**(n-1)``
    seconds (at most ``max_backoff``), plus ``Retry-After`` when the server sends one; a
    ``Retry-After`` beyond ``max_retry_after`` is not waited for: the error is raised."""

    attempts: int = 4
    backoff: float = 0.25
    max_backoff: float = 8.0
    max_retry_after: float = 60.0
    statuses: frozenset[int] = field(default_factory=lambda: frozenset({429, 503}))

    def __post_init__(self) -> None:
        if self.attempts < 1:
            raise ValueError(f"attempts must be at least 1, not {self.attempts}")

    def delay(self, retry: int, retry_after: float | None) -> float:
        """Seconds to wait before retry number ``retry`` (1, 2, ...)."""
        jitter = random.uniform(0.0, min(self.max_backoff, self.backoff * 2 ** (retry - 1)))
        return jitter if retry_after is None else retry_after + jitter


def retry_after_seconds(value: str | None) -> float | None:
    """``Retry-After`` as seconds from now: delta-seconds or an HTTP date; None if absent or unreadable."""
    if not value:
        return None
    if value.strip().isdigit():
        return float(value)
    try:
        return max(0.0, parsedate_to_datetime(value).timestamp() - time.time())
    except (TypeError, ValueError):
        return None


class Attempts:
    """The retry decisions of one call."""

    def __init__(self, policy: RetryPolicy, idempotent: bool) -> None:
        self.policy, self.idempotent, self.made = policy, idempotent, 0

    def after_response(self, response: httpx.Response) -> float | None:
        """Seconds to wait before trying again, or None: the response is the answer."""
        self.made += 1
        if response.status_code not in self.policy.statuses or self.made >= self.policy.attempts:
            return None
        retry_after = retry_after_seconds(response.headers.get("retry-after"))
        if retry_after is not None and retry_after > self.policy.max_retry_after:
            return None
        return self.policy.delay(self.made, retry_after)

    def after_error(self, error: httpx.TransportError, url: str) -> float:
        """Seconds to wait before trying again; ConnectionFailed when the error is final."""
        self.made += 1
        safe = self.idempotent or isinstance(error, _NOTHING_SENT)
        if not safe or self.made >= self.policy.attempts:
            tried = f"after {self.made} attempt{'s' * (self.made > 1)}"
            why = (
                "" if safe else " (not retried: the call is not idempotent and the request may have arrived)"
            )
            failure = f"{type(error).__name__}: {error or 'no details'}"
            raise ConnectionFailed(f"{url}: {failure} {tried}{why}") from error
        return self.policy.delay(self.made, None)
