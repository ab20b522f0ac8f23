"""Per-process folders (uploads, metrics): a starting server removes only dead processes' folders."""

from __future__ import annotations

import os
import socket
from pathlib import Path

from service.calibration.uploads import UploadWorkspace
from service.infra.processes import process_folder, remove_dead_process_folders


def dead_pid() -> int:
    """A pid no process has: pids stay below the kernel's pid_max."""
    return int(Path("/proc/sys/kernel/pid_max").read_text())


def test_a_workspace_is_created_in_this_process_folder(tmp_path: Path) -> None:
    workspace = UploadWorkspace.create(tmp_path)
    assert workspace.root.parent == process_folder(tmp_path)
    assert workspace.root.parent.name == f"{socket.gethostname()}--{os.getpid()}"
    workspace.remove()
    assert not workspace.root.exists()


def test_only_folders_of_stopped_processes_of_this_host_are_removed(tmp_path: Path) -> None:
    mine = UploadWorkspace.create(tmp_path).root
    orphan = process_folder(tmp_path, dead_pid()) / "abc"
    other_host = tmp_path / "some-other-host--1" / "def"
    not_a_process = tmp_path / "notes"
    for folder in (orphan, other_host, not_a_process):
        folder.mkdir(parents=True)
        (folder / "batch.zip").write_bytes(b"x")

    removed = remove_dead_process_folders(tmp_path)

    assert removed == [orphan.parent]
    assert not orphan.parent.exists()
    assert mine.is_dir() and other_host.is_dir() and not_a_process.is_dir()


def test_a_starting_process_removes_a_predecessors_folder_under_its_own_pid(tmp_path: Path) -> None:
    """A container restarted in place after a SIGKILL: its server is pid 1 again, and the
    uploads of the killed pid 1 (never stored) would otherwise stay for as long as it lives."""
    left = process_folder(tmp_path) / "abc"
    left.mkdir(parents=True)
    (left / "batch.zip").write_bytes(b"x")
    assert remove_dead_process_folders(tmp_path) == []  # a running process's own: kept
    assert remove_dead_process_folders(tmp_path, starting=True) == [left.parent]
    assert not left.parent.exists()


def test_a_missing_uploads_folder_is_fine(tmp_path: Path) -> None:
    assert remove_dead_process_folders(tmp_path / "never-created") == []
