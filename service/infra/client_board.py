"""Which predict clients asked lately, across the worker processes of one server (CKS_WORKERS).

Fair shares apply while more than one client is active (``service.api.http.admission``); a
worker that only ever sees a flood's connections would otherwise let it take every place
while the polite client is served by another worker. The board is a small file in /dev/shm,
created and allocated whole by the parent before the workers start (``client_board``), so that
a full disk cannot touch it and a full /dev/shm is an error at start, never a Bus error later;
without it (one worker, or /dev/shm unavailable: logged) each worker judges alone. Each worker
claims a row (``ClientBoard.joined``) and writes only that row: the ``RECENT`` clients it saw
last, when, on how many of its slots each computes, and each one's network; any worker reads
every row, so a client's and a network's compute share hold for the group.
"""

from __future__ import annotations

import fcntl
import hashlib
import logging
import mmap
import os
import time
from collections.abc import Iterator
from contextlib import contextmanager
from pathlib import Path

import numpy as np

from service.infra.processes import process_running

log = logging.getLogger(__name__)

#: The environment variable naming the board for the workers (not a setting: set by the parent).
BOARD_VARIABLE = "KEYPOINT_SERVICE_CLIENT_BOARD"
ROWS = 256  # workers at most (a row of a worker that died is taken again)
RECENT = 8  # clients remembered per worker
REREAD_NS = 50_000_000  # how stale ``several_since`` may be
_FIELDS = 4  # per client: its hash, when it asked (ns), the slots it computes on, its network's hash
_COLUMNS = 1 + _FIELDS * RECENT  # the owner's pid first
_SIZE = ROWS * _COLUMNS * 8


@contextmanager
def client_board(workers: int, folder: Path = Path("/dev/shm")) -> Iterator[Path | None]:
    """In the parent, around the workers' lives: the board (its path in ``BOARD_VARIABLE``), or
    None for one worker or where it cannot be made."""
    if workers < 2:
        yield None
        return
    path = folder / f"cks-clients-{os.getpid()}"
    # One under this process's own name was left by a predecessor killed with SIGKILL (a
    # container restarted in place runs its server as pid 1 again): it is no one's now.
    path.unlink(missing_ok=True)
    try:
        descriptor = os.open(path, os.O_CREAT | os.O_EXCL | os.O_RDWR, 0o600)
        try:
            os.posix_fallocate(descriptor, 0, _SIZE)  # every page now: ENOSPC here, not SIGBUS later
        finally:
            os.close(descriptor)
    except OSError as error:
        path.unlink(missing_ok=True)
        log.warning("no client board in %s (%s): each worker keeps its own fair shares", folder, error)
        yield None
        return
    os.environ[BOARD_VARIABLE] = str(path)
    try:
        yield path
    finally:
        os.environ.pop(BOARD_VARIABLE, None)
        path.unlink(missing_ok=True)


class ClientBoard:
    """This process's row of the board, and what every row says."""

    def __init__(self, memory: mmap.mmap, row: int) -> None:
        self._memory = memory
        self._rows = np.ndarray((ROWS, _COLUMNS), np.int64, memory)
        self._mine = self._rows[row]
        self._several = self._several_networks = False
        self._read_at = -REREAD_NS - 1
        self._noted, self._noted_at = "", 0

    @classmethod
    def joined(cls, path: str | None = None) -> ClientBoard | None:
        """A row of the board named in the environment for this worker (None: no board, or no row
        free; logged: this worker's shares are then its own)."""
        path = path or os.environ.get(BOARD_VARIABLE)
        if not path:
            return None
        try:
            descriptor = os.open(path, os.O_RDWR)
        except OSError as error:
            log.warning("cannot open the client board %s (%s): fair shares per worker", path, error)
            return None
        try:
            memory = mmap.mmap(descriptor, _SIZE)  # ValueError: smaller than a board
            fcntl.flock(descriptor, fcntl.LOCK_EX)  # one worker claims a row at a time
            board = np.ndarray((ROWS, _COLUMNS), np.int64, memory)
            owners = board[:, 0]
            dead = [row for row, pid in enumerate(owners) if pid and not process_running(int(pid))]
            board[dead] = 0  # what a worker that died was computing ends with it
            row = next(row for row, pid in enumerate(owners) if pid == 0)
            owners[row] = os.getpid()
        except (OSError, ValueError, StopIteration) as error:
            log.warning("no row of the client board %s (%r): fair shares per worker", path, error)
            return None
        finally:
            fcntl.flock(descriptor, fcntl.LOCK_UN)  # explicitly: the mapping holds a copy of the descriptor
            os.close(descriptor)
        return cls(memory, row)

    def note(self, client: str, computing: int = 0, network: str | None = None) -> None:
        """``client`` (of ``network``: itself by default) asked now, and computes on ``computing``
        more (or fewer) slots of this worker: in place of its entry, else of an idle one
        (``_replaceable``; an asking alone is not written again within ``REREAD_NS``: admission
        notes each request more than once)."""
        now = time.monotonic_ns()
        if not computing and client == self._noted and now - self._noted_at < REREAD_NS:
            return
        key, entries = _key(client), self._mine[1:].reshape(RECENT, _FIELDS)
        found = np.flatnonzero(entries[:, 0] == key)
        idle = np.flatnonzero(entries[:, 2] == 0)
        if not found.size and (computing < 0 or not idle.size):
            return  # every entry computes: this client goes unseen by the other workers
        index = found[0] if found.size else _replaceable(entries, idle)
        slots = (entries[index, 2] if found.size else 0) + computing
        entries[index] = (key, now, slots, _key(network or client))
        self._noted, self._noted_at = client, now

    def computing(self, client: str) -> int:
        """The slots ``client`` computes on in all the workers."""
        entries = self._entries()
        return int(entries[entries[:, 0] == _key(client), 2].sum())

    def network_computing(self, network: str) -> int:
        """The slots the clients of ``network`` compute on in all the workers."""
        entries = self._entries()
        return int(entries[entries[:, 3] == _key(network), 2].sum())

    def several_since(self, seconds_ago: float) -> bool:
        """Whether more than one client asked the workers in the last ``seconds_ago`` seconds (read
        again at most every ``REREAD_NS``: admission asks several times per request)."""
        self._reread(seconds_ago)
        return self._several

    def several_networks_since(self, seconds_ago: float) -> bool:
        """Whether clients of more than one network asked, as ``several_since``."""
        self._reread(seconds_ago)
        return self._several_networks

    def _reread(self, seconds_ago: float) -> None:
        now = time.monotonic_ns()
        if now - self._read_at > REREAD_NS:
            entries = self._entries()
            recent = entries[entries[:, 1] > now - int(seconds_ago * 1e9)]
            self._several, self._several_networks = (_differ(recent[:, field]) for field in (0, 3))
            self._read_at = now

    def _entries(self) -> np.ndarray:
        """Every entry of the rows of workers."""
        return self._rows[self._rows[:, 0] != 0, 1:].reshape(-1, _FIELDS)


def _replaceable(entries: np.ndarray, idle: np.ndarray) -> int:
    """The idle entry asked longest ago, of a network that has another entry where there is one:
    a flood from many addresses of one network does not push a lone client of another network
    off the board (the other workers would then not hold the flood's network to its share)."""
    networks = entries[:, 3]
    crowded = idle[[np.count_nonzero(networks == networks[i]) > 1 for i in idle]]
    candidates = crowded if crowded.size else idle
    return int(candidates[np.argmin(entries[candidates, 1])])


def _differ(keys: np.ndarray) -> bool:
    return bool(keys.size) and bool((keys != keys[0]).any())


def _key(client: str) -> int:
    """A client's number on the board, the same in every process (``hash`` is not), never 0."""
    return int.from_bytes(hashlib.blake2b(client.encode(), digest_size=7).digest()) + 1
