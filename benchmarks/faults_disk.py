"""A full disk, for the live tests (test_disk_full): a server's data directory (uploads, jobs and
the SQLite store) on a small tmpfs (as root), filled while it receives an upload, while it unzips
one into its job's folder, before a job's request.json is written (the store on PostgreSQL, its
versions table held locked meanwhile: ``intake_held``), or while a job writes its version.
"""

from __future__ import annotations

import io
import json
import shutil
import subprocess
import time
import zipfile
from collections.abc import Callable, Iterator
from concurrent.futures import Future, ThreadPoolExecutor
from contextlib import contextmanager
from pathlib import Path

import psycopg

from tests.live.server import LiveServer
from tests.service_calls import ADMIN_TOKEN

DISK = "40m"
#: the file ``fill`` fills a file system with (``free_space`` deletes it)
FILLER = "disk-full.filler"


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
    """A server with its data directory on a small disk."""
    return LiveServer(data, admin_token=ADMIN_TOKEN, **settings)


def serve_on_held(data: Path, store_url: str) -> LiveServer:
    """``serve_on`` with its store on PostgreSQL, for ``intake_held``."""
    return serve_on(data, store_url=store_url)


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


def audit_entries(server: LiveServer) -> list[dict]:
    return server.client.get("/v1/admin/audit", headers=server.admin).json()["entries"]
