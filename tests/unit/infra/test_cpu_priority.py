"""Background threads compute at a lower CPU priority than the process, for their whole life."""

from __future__ import annotations

import os
import threading

from service.infra.cpu_priority import BACKGROUND_NICE, background_pool, in_background


def _priority() -> tuple[int, bool]:
    return os.getpriority(os.PRIO_PROCESS, 0), in_background()  # 0: this thread, on Linux


def test_a_background_pool_thread_is_nicer_than_the_process() -> None:
    process = os.getpriority(os.PRIO_PROCESS, 0)
    with background_pool(2) as pool:
        nice, marked = pool.submit(_priority).result()
        again = pool.submit(_priority).result()
    assert nice == min(19, process + BACKGROUND_NICE) and marked and again == (nice, True)
    assert _priority() == (process, False)  # this thread, and so the process's others, untouched
    other = []
    thread = threading.Thread(target=lambda: other.append(_priority()))
    thread.start()
    thread.join()
    assert other == [(process, False)]
