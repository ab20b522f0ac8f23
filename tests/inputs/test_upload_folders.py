"""Upload workspaces live in one folder per process; a starting server removes dead processes' folders."""

from __future__ import annotations

import os
import socket
import subprocess
import sys
from pathlib import Path

from service.calibration.uploads import UploadWorkspace, process_uploads_dir, remove_orphaned_uploads


def dead_pid() -> int:
    process = subprocess.Popen([sys.executable, "-c", "pass"])
    process.wait()
    return process.pid


def test_a_workspace_is_created_in_this_process_folder(tmp_path: Path) -> None:
    workspace = UploadWorkspace.create(tmp_path)
    assert workspace.root.parent == process_uploads_dir(tmp_path)
    assert workspace.root.parent.name == f"{socket.gethostname()}--{os.getpid()}"
    workspace.remove()
    assert not workspace.root.exists()


def test_only_folders_of_stopped_processes_of_this_host_are_removed(tmp_path: Path) -> None:
    mine = UploadWorkspace.create(tmp_path).root
    orphan = process_uploads_dir(tmp_path, dead_pid()) / "abc"
    other_host = tmp_path / "some-other-host--1" / "def"
    not_a_process = tmp_path / "notes"
    for folder in (orphan, other_host, not_a_process):
        folder.mkdir(parents=True)
        (folder / "batch.zip").write_bytes(b"x")

    removed = remove_orphaned_uploads(tmp_path)

    assert removed == [orphan.parent]
    assert not orphan.parent.exists()
    assert mine.is_dir() and other_host.is_dir() and not_a_process.is_dir()


def test_a_missing_uploads_folder_is_fine(tmp_path: Path) -> None:
    assert remove_orphaned_uploads(tmp_path / "never-created") == []
