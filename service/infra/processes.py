"""Which process of which host owns something: job rows (``host:pid``) and folders
(``<host>--<pid>``: upload workspaces, Prometheus files), so that a starting server can remove
those of stopped processes without touching another live server's on a shared data directory.
"""

from __future__ import annotations

import logging
import os
import shutil
import socket
from pathlib import Path

log = logging.getLogger(__name__)


def process_owner() -> str:
    """``host:pid``, the name a job's row gives this process."""
    return f"{socket.gethostname()}:{os.getpid()}"


def process_folder(parent: Path, pid: int | None = None) -> Path:
    """``<parent>/<host>--<pid>`` for this process (or ``pid``)."""
    return parent / f"{socket.gethostname()}--{pid or os.getpid()}"


def remove_dead_process_folders(parent: Path, *, starting: bool = False) -> list[Path]:
    """Remove (and return) the folders of this host's stopped processes; ``starting``: one under this
    pid is a predecessor's (a container restarted in place runs its server as pid 1 again)."""
    removed = []
    host, mine = socket.gethostname(), os.getpid() if starting else None
    for folder in sorted(parent.iterdir()) if parent.is_dir() else []:
        owner_host, _, pid = folder.name.rpartition("--")
        if owner_host == host and pid.isdigit() and (int(pid) == mine or not process_running(int(pid))):
            shutil.rmtree(folder, ignore_errors=True)
            removed.append(folder)
    if removed:
        log.info("removed %d folder(s) of stopped processes under %s", len(removed), parent)
    return removed


def process_running(pid: int) -> bool:
    """Whether a process with this pid exists on this host."""
    try:
        os.kill(pid, 0)
    except ProcessLookupError:
        return False
    except PermissionError:  # it exists, under another user
        return True
    return True
