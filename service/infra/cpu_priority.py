"""Threads that compute at background CPU priority: a client with several requests in flight
while others are served (``service.api.http.admission``) computes on them, so the kernel runs a
one-at-a-time client's request first whenever both want a core.

Linux keeps a nice value per thread, so the threads of ``background_pool`` run
``BACKGROUND_NICE`` above the process's for their whole life (a thread may not raise its
priority again without CAP_SYS_NICE). Elsewhere the value is the whole process's, and the pool's
threads keep the process's priority.
"""

from __future__ import annotations

import logging
import os
import sys
import threading
from concurrent.futures import ThreadPoolExecutor

#: how much nicer background threads are: CFS weighs nice 10 at 110 against 1024 at nice 0, so
#: a thread at the process's priority gets about nine tenths of a core they share
BACKGROUND_NICE = 10

log = logging.getLogger(__name__)
_background = threading.local()


def background_pool(workers: int) -> ThreadPoolExecutor:
    """``workers`` threads whose work runs at ``BACKGROUND_NICE`` (on Linux)."""
    return ThreadPoolExecutor(workers, thread_name_prefix="background", initializer=_lower_this_thread)


def in_background() -> bool:
    """Whether this thread is one of a ``background_pool``'s."""
    return getattr(_background, "lowered", False)


def _lower_this_thread() -> None:
    _background.lowered = True
    if sys.platform != "linux":
        return
    try:  # who 0: this thread, on Linux
        os.setpriority(os.PRIO_PROCESS, 0, min(19, os.getpriority(os.PRIO_PROCESS, 0) + BACKGROUND_NICE))
    except OSError as error:  # a sandbox that forbids it: the thread computes at the process's priority
        log.warning("a background thread keeps the process's CPU priority: %s", error)
