"""A full disk and identical uploads, on real servers: the figures of docs/operations.md.

    python -m benchmarks.faults_disk     # as root: it mounts a 40 MiB tmpfs per step

Each disk step starts one ``keypoint-service serve`` with its data directory (uploads, jobs and
the SQLite store) on a fresh 40 MiB tmpfs and fills it: while an upload is received, while one
is unzipped into its job's folder (12,000 one-byte files that take a page each), before a job's
request.json is written (the store on a throwaway PostgreSQL cluster whose versions table is held
locked while the intake reads it, between the two: see ``intake_held``), and while a job writes
its version. Printed: the answers, the bytes left in ``jobs/`` and ``uploads/``, the
audit entry, and whether the service works again once space is freed (no restart). Then four
identical uploads, and a fifth with ``allow_duplicate`` and a reason. About a minute.

The fault generators here are used by the tests too (tests/live/test_disk_full.py).
"""

from __future__ import annotations

import io
import json
import shutil
import subprocess
import sys
import tempfile
import time
import zipfile
from collections.abc import Callable, Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from contextlib import contextmanager
from pathlib import Path

import psycopg

from benchmarks.faults_clients import long_batch
from tests.live.server import LiveServer
from tests.postgres_cluster import PostgresCluster
from tests.service_calls import ADMIN_TOKEN

DISK = "40m"
COPIES = 6  # the samples, 6 times over (7.7 MB zipped): seconds of scoring
#: the file ``fill`` fills a file system with (``free_space`` deletes it)
FILLER = "disk-full.filler"
#: a server whose intake is held (``intake_held``) waits this long for the store
HELD_STORE_TIMEOUT_S = 60


@contextmanager
def small_disk(parent: Path, size: str = DISK) -> Iterator[Path]:
    """A tmpfs of ``size`` mounted at ``parent/data`` (needs root), unmounted on exit."""
    data = parent / "data"
    data.mkdir()
    subprocess.run(["mount", "-t", "tmpfs", "-o", f"size={size}", "tmpfs", str(data)], check=True)
    try:
        yield data
    finally:
        subprocess.run(["umount", str(data)], check=True)


def serve_on(data: Path, **settings: str) -> LiveServer:
    """A server that leaves a small disk to fill (no free-space reserve: CKS_MIN_FREE_DISK_BYTES=0)."""
    return LiveServer(data, admin_token=ADMIN_TOKEN, min_free_disk_bytes=0, **settings)


def serve_on_held(data: Path, store_url: str) -> LiveServer:
    """``serve_on`` with its store on PostgreSQL, patient enough to wait out ``intake_held``."""
    return serve_on(data, store_url=store_url, store_timeout_seconds=str(HELD_STORE_TIMEOUT_S))


def fill(data: Path, leave: int = 0) -> None:
    """Fill the file system of ``data`` until about ``leave`` bytes are free."""
    with open(data / FILLER, "ab") as out:
        try:
            while (free := shutil.disk_usage(data).free) > leave:
                out.write(b"\0" * min(free - leave, 1 << 20))
                out.flush()
        except OSError:  # full before the last chunk fitted
            pass


def free_space(data: Path) -> None:
    (data / FILLER).unlink()


@contextmanager
def intake_held(store_url: str, timeout_s: float = 30.0) -> Iterator[Callable[[], None]]:
    """Hold the versions table of a PostgreSQL store locked (ACCESS EXCLUSIVE): a server's intake,
    which reads the stored versions after it unzipped an upload into its job's folder and before
    it writes the job's request.json (the duplicate check), waits there until the block ends.
    Yields ``wait()``: returns once a server's connection waits on the lock."""
    with psycopg.connect(store_url, autocommit=True) as watcher, psycopg.connect(store_url) as holder:
        holder.execute("LOCK TABLE calib_versions IN ACCESS EXCLUSIVE MODE")
        held_by = holder.info.backend_pid

        def wait() -> None:
            deadline = time.monotonic() + timeout_s
            while time.monotonic() < deadline:
                (waiting,) = watcher.execute(
                    "SELECT count(*) FROM pg_stat_activity WHERE wait_event_type = 'Lock'"
                    " AND datname = current_database() AND pid <> %s",
                    (held_by,),
                ).fetchone()
                if waiting:
                    return
                time.sleep(0.01)
            raise TimeoutError(f"no server waited on the versions table within {timeout_s} s")

        try:
            yield wait
        finally:
            holder.rollback()


def upload_refused_at_job_request(server: LiveServer, store_url: str, body: bytes) -> Future:
    """Send ``body`` and fill the disk once it is unzipped into its job's folder, before the job's
    request.json is written; returns the answer to come."""
    data = server.data_dir
    with ThreadPoolExecutor(1) as sender:
        with intake_held(store_url) as wait:
            answer = sender.submit(server.upload, body)
            wait()
            unzipped = list((data / "jobs").glob("*/batch"))
            assert unzipped and not list((data / "jobs").glob("*/batch.zip")), "the intake waits elsewhere"
            fill(data)
        return answer


def many_small_files(count: int) -> bytes:
    """A zip whose files declare one byte each but take a page each on the disk."""
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w", zipfile.ZIP_DEFLATED) as archive:
        archive.writestr("annotations.json", json.dumps({"images": [], "annotations": [], "categories": []}))
        for number in range(count):
            archive.writestr(f"pad/{number}.txt", b"x")
    return buffer.getvalue()


def kept_files(server: LiveServer) -> list[Path]:
    """The files of jobs' kept uploads and of upload workspaces."""
    return [p for folder in ("jobs", "uploads") for p in (server.data_dir / folder).rglob("*") if p.is_file()]


def kept_bytes(server: LiveServer) -> int:
    return sum(p.stat().st_size for p in kept_files(server))


def audit_entries(server: LiveServer) -> list[dict]:
    return server.client.get("/v1/admin/audit", headers=server.admin).json()["entries"]


def latest_entry(server: LiveServer) -> str:
    entry = audit_entries(server)[0]
    return f"{entry['action']} {entry['outcome']} {entry['details'].get('status', '')}".rstrip()


def refused_upload(server: LiveServer, body: bytes) -> str:
    began = time.perf_counter()
    response = server.upload(body)
    took = time.perf_counter() - began
    return (
        f"{response.status_code} in {took:.2f} s, {kept_bytes(server)} bytes left in jobs/ and uploads/,"
        f" audited: {latest_entry(server)}"
    )


def receive_step(work: Path) -> None:
    body = long_batch(1)
    with small_disk(work) as data, serve_on(data) as server:
        fill(data, leave=len(body) // 2)
        print(f"upload received on a full disk: {refused_upload(server, body)}", flush=True)
        free_space(data)
        print(f"  space freed: the same upload's job {server.calibrate(body)['state']}", flush=True)


def unzip_step(work: Path) -> None:
    with small_disk(work) as data, serve_on(data) as server:
        body = many_small_files(12_000)
        print(f"upload unzipped on a full disk (12,000 files): {refused_upload(server, body)}", flush=True)
        print(f"  then another upload's job {server.calibrate(long_batch(1))['state']}", flush=True)


def request_step(work: Path) -> None:
    body = long_batch(1)
    with PostgresCluster.start() as cluster:
        url = cluster.create_database()
        with small_disk(work) as data, serve_on_held(data, url) as server:
            began = time.perf_counter()
            response = upload_refused_at_job_request(server, url, body).result()
            print(
                f"disk filled before the job's request.json: {response.status_code} in"
                f" {time.perf_counter() - began:.2f} s (the intake held meanwhile),"
                f" {kept_bytes(server)} bytes left in jobs/ and uploads/, audited: {latest_entry(server)}",
                flush=True,
            )
            free_space(data)
            print(f"  space freed: the same upload's job {server.calibrate(body)['state']}", flush=True)


def store_step(work: Path) -> None:
    with small_disk(work) as data, serve_on(data) as server:
        job_id = server.upload(long_batch(COPIES)).json()["id"]
        fill(data)
        job = server.wait_job(job_id)
        kept = (data / "jobs" / job_id).is_dir()
        print(
            f"a job's version written on a full disk: {job['state']}, {job['errors'][0][:60]}...", flush=True
        )
        activation = server.client.post("/v1/admin/calibrations/1/activate", json={}, headers=server.admin)
        print(f"  upload kept: {kept}; an activation meanwhile: {activation.status_code}", flush=True)
        free_space(data)
        time.sleep(1.5)  # the job's writer lands its failed state
        retried = server.client.post(f"/v1/admin/jobs/{job_id}/retry", headers=server.admin)
        new = server.wait_job(retried.json()["id"]) if retried.status_code == 202 else {"state": "-"}
        refusal = [e for e in audit_entries(server) if e["action"] == "activation"][:1]
        audited = refusal[0]["details"].get("status") if refusal else None
        print(
            f"  space freed: the activation's refusal audited ({audited}); retry {retried.status_code},"
            f" its job {new['state']}",
            flush=True,
        )


def duplicates_step(work: Path) -> None:
    body = long_batch(1)
    with LiveServer(work / "data", admin_token=ADMIN_TOKEN) as server:
        server.calibrate(body)
        answers = [server.upload(body) for _ in range(3)]
        named = {r.json().get("duplicate_of") for r in answers}
        print(f"four identical uploads: 202, then {[r.status_code for r in answers]} naming version {named}")
        allowed = server.calibrate(body, allow_duplicate=True, reason="a copy on purpose")
        entry = next(
            e for e in audit_entries(server) if (e["action"], e["outcome"]) == ("upload", "accepted")
        )
        audited = {k: entry["details"].get(k) for k in ("duplicate_of", "why")}
        print(
            f"  with allow_duplicate and a reason: version {allowed['result']['version']}, audited {audited}"
        )


def main(argv: list[str] | None = None) -> int:
    for step in (receive_step, unzip_step, request_step, store_step, duplicates_step):
        with tempfile.TemporaryDirectory(prefix="cks-faults-") as work:
            step(Path(work))
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
