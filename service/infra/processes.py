"""Which process of which host owns something: job rows (``host:pid``) and folders.

Upload workspaces and the Prometheus multiprocess files live in folders of one process
(``<host>--<pid>``), so that a process can remove its own and a starting server can remove
those of processes that stopped without touching another live server's files on a shared
data directory.
"""

from __future__ import annotations

import logging
import os
import shutil
import socket
from pathlib import Path

log = logging.getLogger(__name__)


def process_owner() -> str:
    """The name a job's row gives this process: ``host:pid``."""
    return f"{socket.gethostname()}:{os.getpid()}"


def process_folder(parent: Path, pid: int | None = None) -> Path:
    """``<parent>/<host>--<pid>`` for this process (or ``pid``)."""
    return parent / f"{socket.gethostname()}--{pid or os.getpid()}"


def remove_dead_process_folders(parent: Path, *, starting: bool = False) -> list[Path]:
    """Remove the folders of processes of this host that no longer run; returns them.

    Folders of other hosts (a shared volume) are left to their own servers. ``starting``: this
    process has made none yet, so one under its own pid is a predecessor's that had the same pid
    (a container restarted in place runs its server as pid 1 again).
    """
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
