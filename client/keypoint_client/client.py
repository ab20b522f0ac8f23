"""``KeypointClient`` (blocking) and ``AsyncKeypointClient`` (asyncio): the same methods, one
keep-alive connection pool each, every call retried as its ``RetryPolicy`` says.

A method that is one call is declared once, by the function in ``calls`` that builds the call
(its signature and documentation are the method's); the two clients only differ in how they
send a call and wait, and in the methods made of several calls.
"""

from __future__ import annotations

import asyncio
import functools
import os
import time
import uuid
from collections.abc import AsyncIterator, Callable, Coroutine, Iterable, Iterator, Mapping, Sequence
from pathlib import Path
from typing import TYPE_CHECKING, Any, Generic, ParamSpec, TypeVar, overload

import httpx

from keypoint_client import calls
from keypoint_client.archive import calibration_zip
from keypoint_client.calls import DEFAULT_BATCH_SIZE, Call, JobWatch, PredictRequest
from keypoint_client.errors import ProblemError
from keypoint_client.frames import FrameSending, crop_padding, is_frame
from keypoint_client.images import ImageInput
from keypoint_client.models import Activation, CoverageAudit, Job, PredictResult
from keypoint_client.retry import Attempts, RetryPolicy

if TYPE_CHECKING:
    from typing import Self, Unpack

    from keypoint_client.calls import AuditOptions, PredictOptions, UploadOptions
    from keypoint_client.models import InstanceLike

__version__ = "0.1.0"
T = TypeVar("T")
P = ParamSpec("P")
CHUNK_BYTES = 1 << 20
Source = str | os.PathLike[str]  # a COCO-keypoints folder, or a zip of one
Progress = Callable[[Job], object]


class endpoint(Generic[P, T]):  # noqa: N801 - used like a decorator
    """A client method that sends the call ``build`` makes: it returns the result on a
    ``KeypointClient`` and an awaitable of it on an ``AsyncKeypointClient``."""

    def __init__(self, build: Callable[P, Call[T]]) -> None:
        self.build = build
        self.__doc__ = build.__doc__

    @overload
    def __get__(self, client: None, owner: type[Any]) -> Self: ...
    @overload
    def __get__(self, client: KeypointClient, owner: type[Any]) -> Callable[P, T]: ...
    @overload
    def __get__(
        self, client: AsyncKeypointClient, owner: type[Any]
    ) -> Callable[P, Coroutine[Any, Any, T]]: ...

    def __get__(self, client: Any, owner: type[Any]) -> Any:
        if client is None:
            return self
        build, send = self.build, client._send

        @functools.wraps(build)
        def method(*args: P.args, **kwargs: P.kwargs) -> Any:
            return send(build(*args, **kwargs))

        return method


def _headers(token: str | None, extra: Mapping[str, str] | None) -> dict[str, str]:
    headers = {"User-Agent": f"keypoint-client/{__version__}"}
    if token:
        headers["Authorization"] = f"Bearer {token}"
    return headers | dict(extra or {})


def _request_id() -> str:
    """One per call, the same on each of its attempts, so the service's logs show them together."""
    return uuid.uuid4().hex


class _Endpoints:
    """The methods that are one call each (documented on the builders in ``calls``)."""

    predict_png = endpoint(calls.predict_png)
    model = endpoint(calls.model)
    ready = endpoint(calls.ready)
    job = endpoint(calls.job)
    retry_job = endpoint(calls.retry_job)
    versions = endpoint(calls.versions)
    version = endpoint(calls.version)
    compare = endpoint(calls.compare)
    activate = endpoint(calls.activate)
    activations = endpoint(calls.activations)
    audit = endpoint(calls.audit)
    audits = endpoint(calls.audits)
    coverage_audit = endpoint(calls.coverage_audit)
    drift = endpoint(calls.drift)
    send_feedback = endpoint(calls.send_feedback)
    live_coverage = endpoint(calls.live_coverage)
    calibrate_from_feedback = endpoint(calls.calibrate_from_feedback)
    store = endpoint(calls.store)


class KeypointClient(_Endpoints):
    """A client of the conformal keypoint service at ``base_url``, blocking.

    ``token``: the admin bearer token (only admin calls need one). ``timeout``: seconds per
    attempt of a call, unless the call is given its own. ``retry``: when to try again.
    ``close()`` it, or use it in a ``with`` block, to release its connections.
    """

    def __init__(
        self,
        base_url: str,
        token: str | None = None,
        timeout: float = 30.0,
        *,
        retry: RetryPolicy | None = None,
        headers: Mapping[str, str] | None = None,
    ) -> None:
        self.retry = retry or RetryPolicy()
        self._http = httpx.Client(base_url=base_url, timeout=timeout, headers=_headers(token, headers))
        self._padding: float | None = None  # the model's crop padding, asked once for numpy frames

    def close(self) -> None:
        self._http.close()

    def __enter__(self) -> Self:
        return self

    def __exit__(self, *exc_info: object) -> None:
        self.close()

    def _send(self, call: Call[T]) -> T:
        request_id, attempts = _request_id(), Attempts(self.retry, call.idempotent)
        while True:
            content = None if call.upload is None else _file_chunks(call.upload)
            try:
                response = self._http.request(content=content, **call.request_arguments(request_id))
            except httpx.TransportError as error:
                time.sleep(attempts.after_error(error, f"{self._http.base_url}{call.path}"))
                continue
            delay = attempts.after_response(response)
            if delay is None:
                return call.answer(response, request_id)
            time.sleep(delay)

    def predict(
        self,
        image: ImageInput,
        instances: Sequence[InstanceLike],
        *,
        frame_sending: FrameSending = "regions",
        timeout: float | None = None,
        **options: Unpack[PredictOptions],
    ) -> PredictResult:
        """Prediction sets for one image: JPEG or PNG bytes, a path to one, or a numpy array.
        ``instances``: the objects and their boxes. Options: see ``PredictRequest``.

        A numpy frame of uint8 pixels, (H, W) gray or (H, W, 3) in ``channel_order``, goes to POST
        /v1/predict/frame as ``frame_sending`` says: its boxes' regions as raw pixels (the default),
        as JPEG (lossy: the answer is the JPEG's) or PNG files, or the whole frame raw; the answer
        is the one the whole image's pixels get. Any other array is sent as a PNG."""
        if is_frame(image) and self._padding is None:
            self._padding = crop_padding(self.model(timeout=timeout))
        call = calls.predict_any(image, instances, self._padding, frame_sending, timeout=timeout, **options)
        return self._send(call)

    def predict_many(
        self,
        requests: Iterable[PredictRequest],
        *,
        batch_size: int = DEFAULT_BATCH_SIZE,
        timeout: float | None = None,
    ) -> list[PredictResult | ProblemError]:
        """One answer per request, in order: its result, or the problem that image alone had (a
        ``ProblemError``, returned, not raised). Sent ``batch_size`` images per POST
        /v1/predict/batch (at most 16 images, the service's limit); a problem of a whole
        request (too large, or still 503 after the retries) is raised."""
        answers: list[PredictResult | ProblemError] = []
        for batch in calls.batches(list(requests), batch_size):
            batch_answers = self._send(calls.predict_batch(batch, timeout))
            answers += batch_answers
        return answers

    def upload_calibration(
        self, source: Source, *, timeout: float | None = None, **options: Unpack[UploadOptions]
    ) -> Job:
        """Upload a labeled batch, a COCO-keypoints folder (zipped here) or a zip of one; returns
        its job, queued. Options: see ``UploadOptions``."""
        with calibration_zip(source) as archive:
            return self._send(calls.upload(archive, options, timeout))

    def wait_for_job(
        self,
        job: str | Job,
        *,
        progress: Progress | None = None,
        poll_interval: float = 0.5,
        timeout: float | None = None,
    ) -> Job:
        """Poll a job until it succeeds and return it; ``progress(job)`` hears of every change.
        JobFailed when it fails or is interrupted, JobWaitTimeout after ``timeout`` seconds."""
        watch = JobWatch(progress, poll_interval, timeout)
        while True:
            current = self.job(job)
            delay = watch.next_poll(current)
            if delay is None:
                return current
            time.sleep(delay)

    def calibrate(
        self,
        source: Source,
        *,
        progress: Progress | None = None,
        wait_timeout: float | None = None,
        timeout: float | None = None,
        **options: Unpack[UploadOptions],
    ) -> Job:
        """Upload a batch and wait for its job (``upload_calibration``, then ``wait_for_job``)."""
        job = self.upload_calibration(source, timeout=timeout, **options)
        return self.wait_for_job(job, progress=progress, timeout=wait_timeout)

    def start_audit(
        self, source: Source, *, timeout: float | None = None, **options: Unpack[AuditOptions]
    ) -> Job:
        """Upload a labeled batch (a COCO-keypoints folder, zipped here, or a zip of one) never used
        to calibrate the audited version; returns its audit job, queued. Options: see ``AuditOptions``."""
        with calibration_zip(source) as archive:
            return self._send(calls.start_audit(archive, options, timeout))

    def run_audit(
        self,
        source: Source,
        *,
        progress: Progress | None = None,
        wait_timeout: float | None = None,
        timeout: float | None = None,
        **options: Unpack[AuditOptions],
    ) -> CoverageAudit:
        """Audit a version's coverage on a batch: ``start_audit``, ``wait_for_job``, then the stored audit."""
        job = self.start_audit(source, timeout=timeout, **options)
        finished = self.wait_for_job(job, progress=progress, timeout=wait_timeout)
        return self.coverage_audit(finished, timeout=timeout)

    def rollback(
        self, *, reason: str, to: int | None = None, force: bool = False, timeout: float | None = None
    ) -> Activation:
        """Activate ``to``, by default the version that was active before the current one."""
        number = self.activations(timeout=timeout).previous_version() if to is None else to
        return self.activate(number, reason=reason, force=force, timeout=timeout)


class AsyncKeypointClient(_Endpoints):
    """``KeypointClient`` for asyncio: the same arguments and methods, to be awaited."""

    def __init__(
        self,
        base_url: str,
        token: str | None = None,
        timeout: float = 30.0,
        *,
        retry: RetryPolicy | None = None,
        headers: Mapping[str, str] | None = None,
    ) -> None:
        self.retry = retry or RetryPolicy()
        self._http = httpx.AsyncClient(base_url=base_url, timeout=timeout, headers=_headers(token, headers))
        self._padding: float | None = None  # the model's crop padding, asked once for numpy frames

    async def close(self) -> None:
        await self._http.aclose()

    async def __aenter__(self) -> Self:
        return self

    async def __aexit__(self, *exc_info: object) -> None:
        await self.close()

    async def _send(self, call: Call[T]) -> T:
        request_id, attempts = _request_id(), Attempts(self.retry, call.idempotent)
        while True:
            content = None if call.upload is None else _file_chunks_async(call.upload)
            try:
                response = await self._http.request(content=content, **call.request_arguments(request_id))
            except httpx.TransportError as error:
                await asyncio.sleep(attempts.after_error(error, f"{self._http.base_url}{call.path}"))
                continue
            delay = attempts.after_response(response)
            if delay is None:
                return call.answer(response, request_id)
            await asyncio.sleep(delay)

    async def predict(
        self,
        image: ImageInput,
        instances: Sequence[InstanceLike],
        *,
        frame_sending: FrameSending = "regions",
        timeout: float | None = None,
        **options: Unpack[PredictOptions],
    ) -> PredictResult:
        """See ``KeypointClient.predict``."""
        if is_frame(image) and self._padding is None:
            self._padding = crop_padding(await self.model(timeout=timeout))
        call = calls.predict_any(image, instances, self._padding, frame_sending, timeout=timeout, **options)
        return await self._send(call)

    async def predict_many(
        self,
        requests: Iterable[PredictRequest],
        *,
        batch_size: int = DEFAULT_BATCH_SIZE,
        timeout: float | None = None,
    ) -> list[PredictResult | ProblemError]:
        """See ``KeypointClient.predict_many``."""
        answers: list[PredictResult | ProblemError] = []
        for batch in calls.batches(list(requests), batch_size):
            batch_answers = await self._send(calls.predict_batch(batch, timeout))
            answers += batch_answers
        return answers

    async def upload_calibration(
        self, source: Source, *, timeout: float | None = None, **options: Unpack[UploadOptions]
    ) -> Job:
        """See ``KeypointClient.upload_calibration``."""
        with calibration_zip(source) as archive:
            return await self._send(calls.upload(archive, options, timeout))

    async def wait_for_job(
        self,
        job: str | Job,
        *,
        progress: Progress | None = None,
        poll_interval: float = 0.5,
        timeout: float | None = None,
    ) -> Job:
        """See ``KeypointClient.wait_for_job``."""
        watch = JobWatch(progress, poll_interval, timeout)
        while True:
            current = await self.job(job)
            delay = watch.next_poll(current)
            if delay is None:
                return current
            await asyncio.sleep(delay)

    async def calibrate(
        self,
        source: Source,
        *,
        progress: Progress | None = None,
        wait_timeout: float | None = None,
        timeout: float | None = None,
        **options: Unpack[UploadOptions],
    ) -> Job:
        """See ``KeypointClient.calibrate``."""
        job = await self.upload_calibration(source, timeout=timeout, **options)
        return await self.wait_for_job(job, progress=progress, timeout=wait_timeout)

    async def start_audit(
        self, source: Source, *, timeout: float | None = None, **options: Unpack[AuditOptions]
    ) -> Job:
        """See ``KeypointClient.start_audit``."""
        with calibration_zip(source) as archive:
            return await self._send(calls.start_audit(archive, options, timeout))

    async def run_audit(
        self,
        source: Source,
        *,
        progress: Progress | None = None,
        wait_timeout: float | None = None,
        timeout: float | None = None,
        **options: Unpack[AuditOptions],
    ) -> CoverageAudit:
        """See ``KeypointClient.run_audit``."""
        job = await self.start_audit(source, timeout=timeout, **options)
        finished = await self.wait_for_job(job, progress=progress, timeout=wait_timeout)
        return await self.coverage_audit(finished, timeout=timeout)

    async def rollback(
        self, *, reason: str, to: int | None = None, force: bool = False, timeout: float | None = None
    ) -> Activation:
        """See ``KeypointClient.rollback``."""
        number = (await self.activations(timeout=timeout)).previous_version() if to is None else to
        return await self.activate(number, reason=reason, force=force, timeout=timeout)


def _file_chunks(path: Path) -> Iterator[bytes]:
    with path.open("rb") as file:
        while chunk := file.read(CHUNK_BYTES):
            yield chunk


async def _file_chunks_async(path: Path) -> AsyncIterator[bytes]:
    with path.open("rb") as file:
        while chunk := await asyncio.to_thread(file.read, CHUNK_BYTES):
            yield chunk
