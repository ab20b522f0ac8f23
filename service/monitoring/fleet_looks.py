"""The looks of a fleet counted as one process would count them (a proxy spreading a camera's frames
gives each replica a first frame): a look counts if its first frame continues none of the
``INTERLEAVED_STREAMS`` frames before it among all replicas' (all known) and no other replica's
earlier look is the same image; decided for good once every replica shared its frames up to then.
"""

from __future__ import annotations

import math
from dataclasses import dataclass

import numpy as np

from service.monitoring.looks import INTERLEAVED_STREAMS, NO_KEY, Frame, continues

#: status of a look: it counts for the fleet, it continues another replica's look (NaN: undecided)
COUNTED, CONTINUED = 1.0, 0.0


@dataclass(frozen=True)
class ReplicaLooks:
    """What one replica saw of the looks: its recent frames and its looks, in time order."""

    replica: str
    covered_until: float  # unix seconds: its frames and looks until then are all here
    complete_since: float  # its frames older than this were dropped (0.0: none)
    frame_times: np.ndarray  # (F,) unix seconds, ascending
    frames: tuple[Frame, ...]
    looks: np.ndarray  # (L, 2): unix time of the look's first frame, Z
    statuses: np.ndarray  # (L,): COUNTED, CONTINUED or NaN
    keys: np.ndarray  # (L,) int64: look_key of the look's first frame

    def counted(self, statuses: np.ndarray) -> np.ndarray:
        """(time, Z) of the looks ``statuses`` count."""
        return self.looks[statuses == COUNTED]


def fleet_statuses(replicas: list[ReplicaLooks]) -> list[np.ndarray]:
    """Per replica, each look's status: decided ones kept, others decided on the fleet's frames."""
    if len(replicas) == 1:
        only = replicas[0].statuses
        return [np.where(np.isnan(only), COUNTED, only)]
    frames = _FleetFrames(replicas)
    # per replica, the time each of its look keys was first seen
    first_seen = [dict(zip(r.keys[::-1].tolist(), r.looks[::-1, 0].tolist(), strict=True)) for r in replicas]
    statuses = []
    for index, replica in enumerate(replicas):
        status = replica.statuses.copy()
        for row in np.flatnonzero(np.isnan(status)):
            seen, key = float(replica.looks[row, 0]), int(replica.keys[row])
            repeated = any(
                first.get(key, math.inf) < seen for other, first in enumerate(first_seen) if other != index
            )
            new = key == NO_KEY or (not repeated and frames.starts_a_look(index, seen))
            status[row] = COUNTED if new else CONTINUED
        statuses.append(status)
    return statuses


def settle(own: ReplicaLooks, others: list[ReplicaLooks], read_at: float) -> np.ndarray:
    """The statuses of this replica's looks with those up to ``settled_until`` decided for good."""
    status = fleet_statuses([own, *others])[0]
    keep = np.isnan(own.statuses) & (own.looks[:, 0] > settled_until(others, read_at))
    return np.where(keep, np.nan, status)


def settled_until(others: list[ReplicaLooks], read_at: float) -> float:
    """The time until which every replica's frames are known."""
    return min([read_at, *(other.covered_until for other in others)])


class _FleetFrames:
    """Every replica's shared frames in one time order."""

    def __init__(self, replicas: list[ReplicaLooks]) -> None:
        times = np.concatenate([r.frame_times for r in replicas])
        owners = np.concatenate([np.full(r.frame_times.size, i) for i, r in enumerate(replicas)])
        self._order = np.lexsort((owners, times))
        self._times, self._owners = times[self._order], owners[self._order]
        self._frames = [frame for r in replicas for frame in r.frames]
        self._replicas = replicas

    def starts_a_look(self, replica: int, seen: float) -> bool:
        """Whether that frame continues none of the other replicas' recent frames (False: unknown)."""
        own = self._replicas[replica]
        place = int(np.searchsorted(own.frame_times, seen))
        if place == own.frame_times.size or own.frame_times[place] != seen:
            return False  # its frame left its replica's log: unknown
        frame = own.frames[place]
        end = int(np.searchsorted(self._times, seen))
        start = max(0, end - INTERLEAVED_STREAMS)
        window_start = self._times[start] if end - start == INTERLEAVED_STREAMS else 0.0  # all before
        if any(r.complete_since > window_start for r in self._replicas):
            return False  # some frames of that window were dropped: unknown
        return not any(
            continues(self._frames[self._order[i]], frame)
            for i in range(start, end)
            if self._owners[i] != replica
        )
