"""Errors that carry an HTTP meaning (the API turns them into RFC 9457 problem+json), with a
message that tells the caller what to fix."""

from __future__ import annotations

import errno
from collections.abc import Iterator, Sequence
from contextlib import contextmanager
from typing import Any

from calibration_store import StoreFull


class ServiceError(Exception):
    """Base class: ``status`` and ``title`` are the problem's, ``detail`` the message."""

    status: int = 400
    title: str = "Bad request"

    def __init__(
        self,
        detail: str,
        *,
        errors: list[str] | None = None,
        headers: dict[str, str] | None = None,
        extensions: dict[str, Any] | None = None,
    ) -> None:
        super().__init__(detail)
        self.detail = detail
        self.errors = errors or []
        self.headers = headers or {}
        self.extensions = extensions or {}  # extra members of the problem body (RFC 9457)


class InvalidInput(ServiceError):
    status, title = 422, "Invalid input"


class RequestTimeout(ServiceError):
    status, title = 408, "Request timeout"


class PayloadTooLarge(ServiceError):
    status, title = 413, "Payload too large"


class UnsupportedMediaType(ServiceError):
    status, title = 415, "Unsupported media type"


class NotFound(ServiceError):
    status, title = 404, "Not found"


class Conflict(ServiceError):
    status, title = 409, "Conflict"


class Gone(ServiceError):
    status, title = 410, "Gone"


class InsufficientStorage(ServiceError):
    status, title = 507, "Insufficient storage"


class TooManyRequests(ServiceError):
    status, title = 429, "Too many requests"


class Unavailable(ServiceError):
    status, title = 503, "Service unavailable"


class StoreUnreachable(Unavailable):
    """The calibration store is away: retry after ``Retry-After``; predictions go on from memory."""

    title = "Calibration store unreachable"

    def __init__(self, detail: str, retry_after_s: int = 1) -> None:
        super().__init__(detail, headers={"Retry-After": str(retry_after_s)})


#: what a write on a full file system fails with (no space; the user's quota)
DISK_FULL = frozenset({errno.ENOSPC, errno.EDQUOT})


@contextmanager
def disk_full_refused(what: str) -> Iterator[None]:
    """A write of ``what`` that finds the disk full (or the store's) is a 507."""
    try:
        yield
    except OSError as error:
        if error.errno not in DISK_FULL:
            raise
        raise InsufficientStorage(
            f"the data directory's file system is full: {what} could not be written ({error.strerror})."
            " Nothing of it was kept; retry once space is freed"
        ) from error
    except StoreFull as error:
        raise InsufficientStorage(
            f"the calibration store's disk is full: {what} could not be stored ({error}). Nothing of it"
            " was kept; retry once space is freed"
        ) from error


def capped(items: Sequence[str], limit: int) -> list[str]:
    """The first ``limit`` items, and ``... and N more`` for the rest."""
    more = [f"... and {len(items) - limit} more"] if len(items) > limit else []
    return [*items[:limit], *more]
