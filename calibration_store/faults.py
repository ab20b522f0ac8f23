"""Fault points for fault-injection tests of real processes.

With ``CKS_FAULT=<point>`` in its environment, a process meets a real fault when it reaches
that point. Crash points kill it with SIGKILL, exactly as a power cut or the OOM killer would
stop it there: ``version-written`` (a version, its activation, its job's success and audit
entries are written but not committed) and ``version-committed`` (just committed, nothing else
done). Disk points fill a file system, as another program writing would, just before a write:
``disk-full:<name>`` (see ``fill_disk_point``). Unset, a point costs one environment lookup.
"""

from __future__ import annotations

import errno
import os
import signal
from pathlib import Path

FAULT_ENV = "CKS_FAULT"
#: the file a disk point fills its file system with (delete it to free the space)
FILLER = "disk-full.filler"
_filled: set[str] = set()


def crash_point(name: str) -> None:
    if os.environ.get(FAULT_ENV) == name:
        os.kill(os.getpid(), signal.SIGKILL)


def fill_disk_point(name: str, folder: Path) -> None:
    """With ``CKS_FAULT=disk-full:<name>``, fill the file system of ``folder`` with ``FILLER`` in
    it, the first time this process gets here."""
    if os.environ.get(FAULT_ENV) != f"disk-full:{name}" or name in _filled:
        return
    _filled.add(name)
    descriptor = os.open(folder / FILLER, os.O_WRONLY | os.O_CREAT | os.O_APPEND)
    try:
        while True:
            os.write(descriptor, bytes(1 << 20))
    except OSError as error:
        if error.errno != errno.ENOSPC:
            raise
    finally:
        os.close(descriptor)
