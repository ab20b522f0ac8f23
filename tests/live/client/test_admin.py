"""Calibration administration through the client, against a real server: a COCO folder
uploaded (zipped by the client), its job waited for with progress, compared, activated behind
the guardrails with a reason, rolled back; versions, activations, the audit trail; refusals
as typed exceptions."""

from __future__ import annotations

import asyncio
import json
from datetime import UTC, datetime
from pathlib import Path

import pytest
from keypoint_client import (
    ActivationRefused,
    AsyncKeypointClient,
    Conflict,
    InvalidInput,
    Job,
    JobFailed,
    JobWaitTimeout,
    KeypointClient,
    NotFound,
    Unauthorized,
)
from keypoint_client.archive import zip_coco_folder
from keypoint_client.calls import JobWatch

from tests.live.server import LiveServer
from tests.samples import batch_files, count_instances
from tests.service_calls import ADMIN_TOKEN


def write_folder(folder: Path, doc: dict, files: dict[str, bytes]) -> Path:
    for name, data in {"annotations.json": json.dumps(doc).encode(), **files}.items():
        (folder / name).parent.mkdir(parents=True, exist_ok=True)
        (folder / name).write_bytes(data)
    return folder


def test_upload_wait_activate_roll_back(
    admin: KeypointClient, server: LiveServer, samples_dir: Path, coco: dict, tmp_path: Path
) -> None:
    total = count_instances(coco)
    seen: list[Job] = []
    job = admin.calibrate(samples_dir, progress=seen.append, note="from the client")
    assert (job.state, job.version, job.done, job.total) == ("succeeded", 2, total, total)
    assert seen[-1] == job and [j.done for j in seen] == sorted(j.done for j in seen)
    assert admin.version(2).note == "from the client" and admin.version(2).instances == total

    # The same batch again, as a zip appended to the version holding it: a repeat, refused.
    zip_coco_folder(samples_dir, tmp_path / "batch.zip")
    with pytest.raises(Conflict, match="already counted") as repeated:
        admin.upload_calibration(tmp_path / "batch.zip", append_to=2)
    assert repeated.value.status == 409 and repeated.value.errors
    with pytest.raises(Conflict, match="only an interrupted job can be retried"):
        admin.retry_job(job)

    # 52 instances: below the guardrails' floor, so activating needs force and a reason.
    comparison = admin.compare(2)
    assert not comparison.allowed and comparison.candidate == 2 and comparison.against == 1
    with pytest.raises(ActivationRefused) as refused:
        admin.activate(2, reason="a pilot")
    assert refused.value.status == 409 and refused.value.comparison.problems == comparison.problems
    with pytest.raises(InvalidInput, match="force=true needs a reason"):
        admin.activate(2, force=True)
    activation = admin.activate(2, reason="a pilot batch", force=True)
    assert (activation.version, activation.reason, activation.who) == (2, "a pilot batch", "admin")
    listed = admin.versions()
    assert listed.active_version == 2 and [v.version for v in listed.versions] == [1, 2]

    assert admin.rollback(reason="pilot over").version == 1
    assert [a.version for a in admin.activations().activations] == [1, 2, 1]
    page = admin.audit(limit=2)
    assert [(e.action, e.reason) for e in page.entries][0] == ("rollback", "pilot over")
    older = admin.audit(before=page.next_before, limit=2)
    assert max(e.seq for e in older.entries) < min(e.seq for e in page.entries)
    assert admin.store().kind == "sqlite" and admin.store().active_version == 1

    async def roll_forward() -> int:
        async with AsyncKeypointClient(server.url, token=ADMIN_TOKEN) as client:
            return (await client.rollback(reason="pilot again", force=True)).version

    assert asyncio.run(roll_forward()) == 2 and admin.versions().active_version == 2


def test_a_failed_job_and_other_refusals_are_typed(
    admin: KeypointClient, server: LiveServer, samples_dir: Path, coco: dict, tmp_path: Path
) -> None:
    doc, files = batch_files(samples_dir, coco, images=3)
    broken = doc["images"][1]["file_name"]
    files[broken] = files[broken][: len(files[broken]) // 2]  # truncated: its header is intact
    folder = write_folder(tmp_path / "broken", doc, files)
    versions = admin.versions().versions

    with pytest.raises(JobFailed) as failed:
        admin.calibrate(folder)
    assert failed.value.job.state == "failed"
    assert any(broken in error and "cannot be decoded" in error for error in failed.value.job.errors)

    async def calibrate_async() -> JobFailed:
        async with AsyncKeypointClient(server.url, token=ADMIN_TOKEN) as client:
            with pytest.raises(JobFailed) as raised:
                await client.calibrate(folder)
            return raised.value

    assert asyncio.run(calibrate_async()).job.errors == failed.value.job.errors
    assert admin.versions().versions == versions

    with pytest.raises(NotFound):
        admin.job("no-such-job")
    with (
        KeypointClient(server.url, token="wrong-token") as intruder,
        pytest.raises(Unauthorized) as unauthorized,
    ):
        intruder.versions()
    assert unauthorized.value.status == 401 and "Bearer" in unauthorized.value.detail
    with pytest.raises(ValueError, match="has no annotations.json"):
        admin.upload_calibration(tmp_path)


def test_waiting_ends_at_its_timeout() -> None:
    now = datetime.now(UTC)
    running = Job(
        id="j",
        kind="calibration",
        state="running",
        done=3,
        total=9,
        errors=[],
        result={},
        created_at=now,
        finished_at=None,
    )
    heard: list[Job] = []
    watch = JobWatch(heard.append, poll_interval=0.5, timeout=60)
    assert watch.next_poll(running) == 0.5 and watch.next_poll(running) == 0.5 and heard == [running]
    with pytest.raises(JobWaitTimeout, match="still running \\(3/9 instances\\) after 0 s"):
        JobWatch(None, poll_interval=0.5, timeout=0).next_poll(running)
