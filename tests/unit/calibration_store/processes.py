"""Start and collect child processes for the store tests (spawn: no inherited state)."""

from __future__ import annotations

import multiprocessing
from collections.abc import Callable, Sequence
from typing import Any

CONTEXT = multiprocessing.get_context("spawn")


def run_together(
    target: Callable[..., None], args_for: Sequence[tuple[Any, ...]], timeout: float = 60
) -> list[Any]:
    """Run target(*args, barrier, ..., results) in len(args_for) processes; collect results.

    Each args tuple gets the shared barrier inserted after its first element (the URL)
    and the result queue appended.
    """
    barrier = CONTEXT.Barrier(len(args_for))
    results = CONTEXT.Queue()
    procs = [CONTEXT.Process(target=target, args=(args[0], barrier, *args[1:], results)) for args in args_for]
    for proc in procs:
        proc.start()
    collected = [results.get(timeout=timeout) for _ in procs]
    for proc in procs:
        proc.join(timeout=timeout)
        assert proc.exitcode == 0, f"worker exited with {proc.exitcode}"
    return collected
