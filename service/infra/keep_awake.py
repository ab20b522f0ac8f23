"""Keeping the other cores awake while a lone request's model run spreads over them.

An idle core halts, and on a virtual machine waking it again costs far more than the pieces of
work onnxruntime hands its intra-op threads, which sleep between pieces: a 1080p frame's 4 boxes
took 11.9 ms back to back and 14.4 ms at a camera's cadence, the difference in the model's run
(docs/operations.md, Idle cores between frames). While such a run computes, one thread per
other core busy-waits at the lowest priority (``SCHED_IDLE``), so those cores do not halt
between the run's pieces, and give way at once to any thread with work, the run's own
included. Between runs they sleep.

The threads are the C extension ``_keep_awake``'s (Linux): they never take the interpreter
lock, which a thread of the lowest priority could otherwise hold up the others with. Without
the extension, nothing is kept awake.
"""

from __future__ import annotations

import os
from collections.abc import Iterator
from contextlib import contextmanager

try:
    from service.infra import _keep_awake
except ImportError:  # not built (no C compiler, not Linux): the cores sleep between pieces
    _keep_awake = None

_KEEP_AWAKE_VERSION = 2  # native/keep_awake.c's VERSION: an extension built from older sources is not used
_native = _keep_awake if getattr(_keep_awake, "VERSION", None) == _KEEP_AWAKE_VERSION else None


class KeepAwake:
    """Keeps ``cores`` cores awake while ``during`` is entered (by any number of runs at once);
    its threads start at the first run."""

    def __init__(self, cores: int) -> None:
        self.cores = cores

    @contextmanager
    def during(self) -> Iterator[None]:
        assert _native is not None
        _native.start(self.cores)
        _native.begin()
        try:
            yield
        finally:
            _native.end()


def keep_awake_available() -> bool:
    """Whether cores can be kept awake (the C extension built from these sources)."""
    return _native is not None


def keep_awake(run_threads: int) -> KeepAwake | None:
    """Keeping awake the other cores of a run on ``run_threads`` threads, where those are all
    the cores this process may run on (its CPU affinity: under a CPU quota narrower than that,
    the run's threads may land on any of them); else, or without the extension, None."""
    if not keep_awake_available() or run_threads < 2 or run_threads != len(os.sched_getaffinity(0)):
        return None
    return KeepAwake(run_threads - 1)
