"""Which of two ways to run a lone request is faster on this machine now: measured, not assumed.

Giving one request every core (more intra-op threads, or its crops split across streams) pays
on an idle machine and costs on a busy one, where the extra threads wait for cores that other
processes hold. So the detector times both ways on the lone requests it runs and picks the one
that has been faster lately, per crop count; every ``explore``-th lone run of a crop count
tries the other way, so the choice follows the machine's load.
"""

from __future__ import annotations

import collections
import statistics
import threading
from dataclasses import dataclass, field

NARROW, WIDE = False, True


@dataclass
class _Estimate:
    seconds: dict[bool, collections.deque[float]] = field(default_factory=dict)  # way -> recent runs
    runs: int = 0

    def median(self, way: bool) -> float:
        return statistics.median(self.seconds[way])


class FasterWay:
    """The recent lone runs' seconds, per crop count, for the narrow and the wide way: the way with
    the smaller median (robust to the odd run that waited for a core) is picked."""

    def __init__(self, explore: int = 8, window: int = 9) -> None:
        self._explore, self._window = explore, window
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
            faster = min(estimate.seconds, key=estimate.median)
            return (not faster) if estimate.runs % self._explore == 0 else faster

    def record(self, crops: int, way: bool, seconds: float) -> None:
        with self._lock:
            estimate = self._estimates.setdefault(crops, _Estimate())
            estimate.seconds.setdefault(way, collections.deque(maxlen=self._window)).append(seconds)
