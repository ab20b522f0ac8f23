"""Exceptions raised by the calibration store (the service maps them to HTTP statuses)."""

from __future__ import annotations


class StoreError(Exception):
    """Base class of every error the store raises on purpose."""


class VersionNotFound(StoreError, LookupError):
    """No calibration version with this number exists for this model hash (HTTP 404)."""

    def __init__(self, model_hash: str, number: int) -> None:
        super().__init__(f"calibration version {number} does not exist for model {model_hash}")
        self.model_hash = model_hash
        self.number = number


class DuplicateVersion(StoreError):
    """A version with the same content key is stored already (at most one per model): nothing was
    written (HTTP 409)."""

    def __init__(self, model_hash: str, number: int) -> None:
        super().__init__(f"calibration version {number} of model {model_hash} has the same content")
        self.model_hash = model_hash
        self.number = number


class JobNotFound(StoreError, LookupError):
    """No job with this id is stored (never created, or pruned)."""

    def __init__(self, job_id: str) -> None:
        super().__init__(f"no job {job_id!r} is stored")
        self.job_id = job_id


class JobFinished(StoreError):
    """The job is already in a final state; a finished job is never rewritten."""

    def __init__(self, job_id: str, state: str) -> None:
        super().__init__(f"job {job_id!r} is already {state}; a finished job cannot change")
        self.job_id = job_id
        self.state = state


class JobExists(StoreError, ValueError):
    """create_job was given the id of a job that is already stored."""

    def __init__(self, job_id: str) -> None:
        super().__init__(f"a job with id {job_id!r} is already stored; ids must be unique")
        self.job_id = job_id


class SchemaVersionError(StoreError):
    """The database schema is newer than this code understands (refuse to touch it)."""


class StoreUnavailable(StoreError):
    """The database cannot be reached or stayed locked too long (HTTP 503; retry later)."""


class StoreFull(StoreUnavailable):
    """The database's disk is full: nothing of the operation was written (HTTP 507; retry
    once space is freed)."""
