"""Background calibration jobs: a bounded worker pool and the state clients poll."""

from __future__ import annotations

import logging
import threading
import uuid
from collections import OrderedDict
from collections.abc import Callable
from concurrent.futures import ThreadPoolExecutor
from dataclasses import dataclass, field, replace
from datetime import UTC, datetime
from typing import Literal

from service.errors import ServiceError
from service.metrics import CALIBRATION_JOBS

log = logging.getLogger(__name__)
JobStateName = Literal["queued", "running", "succeeded", "failed"]


@dataclass(frozen=True)
class Job:
    """A snapshot of one job; the runner replaces it as the job advances."""

    id: str
    kind: str
    state: JobStateName = "queued"
    done: int = 0
    total: int = 0
    errors: tuple[str, ...] = ()
    result: dict = field(default_factory=dict)
    created_at: datetime = field(default_factory=lambda: datetime.now(UTC))
    finished_at: datetime | None = None


class JobProgress:
    """Handed to a running job so it can report progress without knowing the runner."""

    def __init__(self, runner: JobRunner, job_id: str) -> None:
        self._runner, self._id = runner, job_id

    def set_total(self, total: int) -> None:
        self._runner._update(self._id, total=total)

    def advance(self, count: int = 1) -> None:
        self._runner._advance(self._id, count)


JobFunction = Callable[[JobProgress], dict]


class JobRunner:
    """Runs jobs on ``workers`` threads and remembers the latest ``keep`` of them."""

    def __init__(self, workers: int = 1, keep: int = 1000) -> None:
        self._pool = ThreadPoolExecutor(max_workers=workers, thread_name_prefix="calibration")
        self._jobs: OrderedDict[str, Job] = OrderedDict()
        self._lock = threading.Lock()
        self._keep = keep

    def submit(self, kind: str, function: JobFunction, total: int = 0) -> Job:
        job = Job(id=uuid.uuid4().hex, kind=kind, total=total)
        with self._lock:
            self._jobs[job.id] = job
            while len(self._jobs) > self._keep:
                self._jobs.popitem(last=False)
        self._pool.submit(self._run, job.id, function)
        return job

    def get(self, job_id: str) -> Job | None:
        with self._lock:
            return self._jobs.get(job_id)

    def shutdown(self) -> None:
        self._pool.shutdown(wait=True, cancel_futures=True)

    def _run(self, job_id: str, function: JobFunction) -> None:
        self._update(job_id, state="running")
        try:
            result = function(JobProgress(self, job_id))
        except ServiceError as error:
            self._finish(job_id, "failed", errors=(error.detail, *error.errors))
        except Exception as error:  # a job must never take the worker down with it
            log.exception("calibration job %s failed", job_id)
            self._finish(job_id, "failed", errors=(f"internal error: {type(error).__name__}: {error}",))
        else:
            self._finish(job_id, "succeeded", result=result)

    def _finish(self, job_id: str, state: JobStateName, **changes) -> None:
        CALIBRATION_JOBS.labels(state).inc()
        self._update(job_id, state=state, finished_at=datetime.now(UTC), **changes)

    def _update(self, job_id: str, **changes) -> None:
        with self._lock:
            if job_id in self._jobs:
                self._jobs[job_id] = replace(self._jobs[job_id], **changes)

    def _advance(self, job_id: str, count: int) -> None:
        with self._lock:
            job = self._jobs.get(job_id)
            if job is not None:
                self._jobs[job_id] = replace(job, done=job.done + count)
