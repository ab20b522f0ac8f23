"""Keeping the other cores awake while a lone request's model run spreads over them.

An idle core halts, and on a virtual machine waking it again costs far more than the pieces of
work onnxruntime hands its intra-op threads, which sleep between pieces: after the service had
sat idle between frames, as it does at a camera's cadence, a lone request's run of 4 crops on 2
threads took 9.3 ms instead of 5.4 ms. While such a run computes, one thread per other core
busy-waits at the lowest priority (``SCHED_IDLE``), so those cores do not halt between the
run's pieces, and give way at once to any thread with work, the run's own included.

The threads wait in glibc's ``pthread_spin_lock`` (through ctypes, which releases the
interpreter lock) on a lock that the run holds, and sleep between runs. Where the lowest
priority or the spin lock is not available, nothing is kept awake.
"""

from __future__ import annotations

import ctypes
import ctypes.util
import logging
import os
import threading
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from functools import cache
from typing import NamedTuple

log = logging.getLogger(__name__)

SpinCall = Callable[..., int]


class SpinLockCalls(NamedTuple):
    """libc's ``pthread_spin_*`` functions (what an unlocked lock holds differs between builds:
    ``init`` says)."""

    init: SpinCall
    lock: SpinCall
    try_lock: SpinCall
    unlock: SpinCall


class KeepAwake:
    """``cores`` lowest-priority threads that busy-wait while ``during`` is entered (by any number
    of callers at once); started at the first use."""

    def __init__(self, cores: int, calls: SpinLockCalls) -> None:
        self._cores, self._calls = cores, calls
        self._spin_lock = ctypes.c_int()  # a pthread_spinlock_t is an int
        self._address = ctypes.c_void_p(ctypes.addressof(self._spin_lock))
        calls.init(self._address, 0)  # private to this process
        self._wanted = threading.Event()  # set only while the spin lock is held for a run
        self._users, self._held, self._state = 0, False, threading.Lock()
        self.threads: list[threading.Thread] = []

    @contextmanager
    def during(self) -> Iterator[None]:
        """The other cores busy-wait until this block ends (unless a waiting thread happens to
        hold the spin lock for its instant between two runs: then this run goes without)."""
        with self._state:
            self._users += 1
            if self._users == 1:
                self._start()
                self._held = self._calls.try_lock(self._address) == 0
                if self._held:
                    self._wanted.set()
        try:
            yield
        finally:
            with self._state:
                self._users -= 1
                if self._users == 0 and self._held:
                    self._wanted.clear()
                    self._calls.unlock(self._address)
                    self._held = False

    def _start(self) -> None:
        while len(self.threads) < self._cores:
            thread = threading.Thread(target=self._wait_awake, name="keep-awake", daemon=True)
            thread.start()
            self.threads.append(thread)

    def _wait_awake(self) -> None:
        try:
            os.sched_setscheduler(0, os.SCHED_IDLE, os.sched_param(0))  # this thread only (Linux)
        except OSError as error:  # never busy-wait beside other work at its priority
            log.warning("cores are not kept awake during lone runs: %s", error)
            return
        while True:
            self._wanted.wait()
            self._calls.lock(self._address)  # busy-waits until the run releases it
            self._calls.unlock(self._address)


def keep_awake(run_threads: int) -> KeepAwake | None:
    """This process's threads keeping awake the other cores of a run on ``run_threads`` threads,
    where those are all the cores it may run on (its CPU affinity: under a CPU quota narrower
    than that, the run's threads may land on any of them); else, or where the lowest priority or
    glibc's spin locks are missing, None."""
    if run_threads < 2 or run_threads != len(os.sched_getaffinity(0)) or not hasattr(os, "SCHED_IDLE"):
        return None
    return _shared(run_threads - 1)


@cache
def _shared(cores: int) -> KeepAwake | None:
    spin_lock = glibc_spin_lock()
    return None if spin_lock is None else KeepAwake(cores, spin_lock)


@cache
def glibc_spin_lock() -> SpinLockCalls | None:
    """libc's spin lock functions, or None where it has none."""
    try:
        libc = ctypes.CDLL(ctypes.util.find_library("c"))
        calls = SpinLockCalls(
            libc.pthread_spin_init,
            libc.pthread_spin_lock,
            libc.pthread_spin_trylock,
            libc.pthread_spin_unlock,
        )
    except (OSError, AttributeError, TypeError):
        return None
    calls.init.argtypes = [ctypes.c_void_p, ctypes.c_int]
    for call in calls[1:]:
        call.argtypes = [ctypes.c_void_p]
    for call in calls:
        call.restype = ctypes.c_int
    return calls
