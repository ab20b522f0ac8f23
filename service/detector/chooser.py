"""Which of two ways to run a lone request is faster on this machine now: measured, not assumed.

Giving one request every core (more intra-op threads, or its crops split across streams) pays
on an idle machine and costs on a busy one, where the extra threads wait for cores that other
processes hold. So the detector times both ways on the lone requests it runs and picks the one
that has been faster lately, per crop count; every ``explore``-th lone run of a crop count
tries the other way, so the choice follows the machine's load.
"""

from __future__ import annotations

import threading
from dataclasses import dataclass, field

NARROW, WIDE = False, True


@dataclass
class _Estimate:
    seconds: dict[bool, float] = field(default_factory=dict)  # way -> moving average
    runs: int = 0


class FasterWay:
    """Moving averages of lone runs' seconds, per crop count, for the narrow and the wide way."""

    def __init__(self, explore: int = 8, weight: float = 0.2) -> None:
        self._explore, self._weight = explore, weight
        self._estimates: dict[int, _Estimate] = {}
        self._lock = threading.Lock()

    def pick(self, crops: int) -> bool:
        """WIDE or NARROW for the next lone run of ``crops`` crops."""
        with self._lock:
            estimate = self._estimates.setdefault(crops, _Estimate())
            estimate.runs += 1
            for way in (WIDE, NARROW):  # each way is timed before any is preferred
                if way not in estimate.seconds:
                    return way
            faster = min(estimate.seconds, key=estimate.seconds.__getitem__)
            return (not faster) if estimate.runs % self._explore == 0 else faster

    def record(self, crops: int, way: bool, seconds: float) -> None:
        with self._lock:
            estimate = self._estimates.setdefault(crops, _Estimate())
            before = estimate.seconds.get(way)
            estimate.seconds[way] = seconds if before is None else before + self._weight * (seconds - before)
