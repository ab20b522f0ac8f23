"""A server removes its own upload folder when it stops (uploads of jobs cancelled at shutdown)."""

from __future__ import annotations

from pathlib import Path

from service.calibration.uploads import process_uploads_dir
from tests.live.server import LiveServer
from tests.service_calls import ADMIN_TOKEN


def test_stopping_removes_this_process_upload_folder(tmp_path: Path) -> None:
    server = LiveServer(tmp_path / "data", admin_token=ADMIN_TOKEN).start()
    try:
        own = process_uploads_dir(server.uploads_dir, server.process.pid)
        leftover = own / "cancelled-job-upload"  # what a job cancelled at shutdown leaves behind
        leftover.mkdir(parents=True)
        (leftover / "batch.zip").write_bytes(b"zip")
        other = process_uploads_dir(server.uploads_dir, server.process.pid + 1) / "another-server-upload"
        other.mkdir(parents=True)
    finally:
        server.stop()
    assert "Application shutdown complete" in server.log(), server.log()  # a graceful stop
    assert not own.exists(), "the stopped server left its upload folder"
    assert other.is_dir(), "a server removed another process's uploads"
