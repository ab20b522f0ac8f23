"""Requests being computed in every worker process of one server: is this request alone?

A request alone on the machine may run wide (every core, see ``runtime.Detector.run``); with
several uvicorn workers (CKS_WORKERS) a process's own count misses the other workers'
requests, and two "lone" requests in two workers would each take every core. So the serving
parent creates a small shared file (``share_activity``) and each worker keeps its count in its
own slot of it, a memory-mapped 64-bit integer that only it writes; ``total`` sums the slots.
Reads are not synchronized with the other workers' writes: the total is a hint, a moment
stale at worst, and a wrong hint costs one request its faster way, never a wrong result.

A worker claims its slot with a lock on that slot's bytes (``fcntl.lockf``), which the kernel
drops when the process ends however it ends; a starting worker zeroes the slots no live worker
holds, so the count of a worker that died mid-request does not outlive its replacement.
"""

from __future__ import annotations

import fcntl
import mmap
import os
import shutil
import threading
from pathlib import Path

from service.runtime.processes import process_folder

ACTIVITY_ENV = "KEYPOINT_SERVICE_ACTIVITY_FILE"  # set by the parent, read by its workers
SLOTS = 128  # CKS_WORKERS is at most 64; a replacement may start before its predecessor is reaped
_SLOT = 8  # bytes: one int64 count


class Activity:
    """This process's requests being computed and, with ``shared`` (a file of ``SLOTS`` counts
    made by ``share_activity``), those of every worker of the server (``total``)."""

    def __init__(self, shared: Path | None = None) -> None:
        self._lock = threading.Lock()
        self._mine = 0
        self._file = self._map = self._counts = None
        self._slot = 0
        if shared is not None:
            self._file = open(shared, "r+b")  # noqa: SIM115 - held open: it holds the slot's lock
            self._map = mmap.mmap(self._file.fileno(), SLOTS * _SLOT)
            self._counts = memoryview(self._map).cast("q")
            self._slot = self._claim_slot()

    def enter(self) -> None:
        with self._lock:
            self._mine += 1
            self._publish()

    def leave(self) -> None:
        with self._lock:
            self._mine -= 1
            self._publish()

    def total(self) -> int:
        """Requests being computed now, in every worker (this process's own when not shared)."""
        return sum(self._counts) if self._counts is not None else self._mine

    def close(self) -> None:
        if self._counts is not None:
            self._counts[self._slot] = 0
            self._counts.release()
            self._map.close()
            self._file.close()  # drops the slot's lock
            self._counts = None

    def _publish(self) -> None:
        if self._counts is not None:
            self._counts[self._slot] = self._mine

    def _claim_slot(self) -> int:
        """Lock the first free slot, for the life of the process; zero the other free ones."""
        mine = None
        for slot in range(SLOTS):
            if not _try_lock(self._file.fileno(), slot):
                continue  # a live worker's
            self._counts[slot] = 0
            if mine is None:
                mine = slot
            else:
                fcntl.lockf(self._file.fileno(), fcntl.LOCK_UN, _SLOT, slot * _SLOT, os.SEEK_SET)
        if mine is None:
            raise RuntimeError(f"all {SLOTS} activity slots of {self._file.name} are held by live processes")
        return mine


def _try_lock(fd: int, slot: int) -> bool:
    try:
        fcntl.lockf(fd, fcntl.LOCK_EX | fcntl.LOCK_NB, _SLOT, slot * _SLOT, os.SEEK_SET)
    except OSError:  # EACCES or EAGAIN: another process holds it
        return False
    return True


def worker_activity() -> Activity:
    """The activity of this process, shared with the server's other workers when the parent
    made a file for them (``share_activity``)."""
    path = os.environ.get(ACTIVITY_ENV)
    return Activity(Path(path) if path else None)


def share_activity(parent: Path) -> Path:
    """Call in the serving parent before its workers start: a zeroed file of slots in this
    parent's folder (``<parent>/<host>--<pid>``), named to the workers in the environment;
    returns the folder (remove it at exit)."""
    folder = process_folder(parent)
    shutil.rmtree(folder, ignore_errors=True)
    folder.mkdir(parents=True)
    path = folder / "activity"
    path.write_bytes(bytes(SLOTS * _SLOT))
    os.environ[ACTIVITY_ENV] = str(path)
    return folder
