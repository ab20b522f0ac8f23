"""Looks counted once in a fleet: one camera's frames spread by a proxy over several replicas
count the looks one process would have counted, and raise the alarm one process would have.

Drift monitors in one test process, each with its own connection to one real store (a SQLite
file, a real PostgreSQL), share their frames and looks as server processes do; a monitor
without a store, fed the same frames, is the one process they must agree with.
"""

from __future__ import annotations

import io
import json
import time
from collections.abc import Iterator
from contextlib import ExitStack
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import pytest

from calibration_store import open_store
from service.conformal import HeatmapStatistics, ball_shapes
from service.monitoring.drift_monitor import DriftMonitor, DriftReport
from service.monitoring.drift_shares import DriftShares, decode_share
from service.monitoring.fleet_looks import CONTINUED, COUNTED, ReplicaLooks, fleet_statuses, settle
from service.monitoring.looks import Frame
from tests.unit.monitoring.test_drift_monitor import MANIFEST, _statistics, _table
from tests.unit.monitoring.test_looks import SEQUENTIAL, _frame

MODEL = "fleet-looks-model"
INTERVAL = 2.0  # seconds: the tests drive the shares themselves; a share is stale after 5 of these


@dataclass(frozen=True)
class Request:
    frame: Frame
    statistics: HeatmapStatistics


def _scenes(rng: np.random.Generator, first: int, count: int, blur: float, frames: int = 6) -> list[Request]:
    """``count`` scenes of a camera (two objects, a slow pan), ``frames`` frames each."""
    requests = []
    for scene in range(first, first + count):
        for k in range(frames):
            frame = _frame(("duck", 10 + 100 * scene + 2 * k, 50), ("mug", 300, 80 + 100 * scene + k))
            channels = sum(len(MANIFEST.object(name).keypoints) for name in frame.objects)
            requests.append(Request(frame, _statistics(rng, channels, blur)))
    return requests


def _record(monitor: DriftMonitor, request: Request) -> None:
    channels = np.concatenate([MANIFEST.object(name).keypoints for name in request.frame.objects])
    shapes = ball_shapes(np.full(channels.size, 10.0))
    monitor.record(channels, request.statistics, "cov", shapes, request.frame)


class Fleet:
    """Replicas on one store, each with its connection; a proxy that sends them requests in turn."""

    def __init__(self, store_url: str, replicas: int, table, stack: ExitStack) -> None:
        self.store = stack.enter_context(open_store(store_url))
        self.monitors = []
        for name in "abcdefgh"[:replicas]:
            shares = DriftShares(stack.enter_context(open_store(store_url)), MODEL, INTERVAL, replica=name)
            self.monitors.append(DriftMonitor(MANIFEST, lambda: (1, table), SEQUENTIAL, shares))
        for monitor in self.monitors:  # as when they start: each row says its replica is in the fleet
            monitor.share()
        self._turn = 0

    def send(self, requests: list[Request]) -> None:
        for request in requests:
            _record(self.monitors[self._turn % len(self.monitors)], request)
            self._turn += 1

    def settle(self) -> list[DriftReport]:
        """Two rounds of shares (as each replica's thread writes its own every interval), then
        every replica's answer."""
        for _ in range(2):
            time.sleep(INTERVAL / 2)  # past each replica's read cache of the others' rows
            for monitor in self.monitors:
                monitor.share()
        time.sleep(INTERVAL / 2)
        return [monitor.report() for monitor in self.monitors]

    def shared(self) -> list[ReplicaLooks]:
        rows = self.store.monitor_shares(MODEL, "drift")
        return [decode_share(row.replica, row.updated_at.timestamp(), row.payload).seen for row in rows]


@pytest.fixture
def stack() -> Iterator[ExitStack]:
    with ExitStack() as opened:
        yield opened


def _agree(fleet: list[DriftReport], alone: DriftReport, replicas: int) -> None:
    assert alone.sequential is not None
    for report in fleet:
        assert report.replicas == replicas, report.replicas
        assert report.sequential is not None
        assert report.sequential.looks == alone.sequential.looks, (report.sequential, alone.sequential)
        assert report.sequential.frames == alone.sequential.frames
        assert report.alarm == alone.alarm
        assert report.sequential.evidence == pytest.approx(alone.sequential.evidence, rel=1e-9)


def test_a_camera_spread_over_two_replicas_counts_the_looks_of_one_process(
    store_url: str, stack: ExitStack
) -> None:
    rng = np.random.default_rng(5)
    table = _table(rng)
    alone = DriftMonitor(MANIFEST, lambda: (1, table), SEQUENTIAL)
    fleet = Fleet(store_url, 2, table, stack)
    quiet, shifted = _scenes(rng, 0, 30, blur=1.0), _scenes(rng, 30, 30, blur=1.6)

    for requests, looks, alarm in ((quiet, 30, False), (shifted, 60, True)):
        for request in requests:
            _record(alone, request)
        fleet.send(requests)
        reports = fleet.settle()
        expected = alone.report()
        assert expected.sequential.looks == looks and expected.alarm == alarm
        _agree(reports, expected, replicas=2)

    shared = fleet.shared()
    assert all(not np.isnan(replica.statuses).any() for replica in shared)  # every look decided
    own_looks = sum(replica.looks.shape[0] for replica in shared)
    assert own_looks == 2 * 60  # each replica saw every scene start: each counted it alone
    assert sum(int((replica.statuses == COUNTED).sum()) for replica in shared) == 60


def test_images_replayed_over_three_replicas_count_once(tmp_path: Path, stack: ExitStack) -> None:
    """A client cycling over 20 images through a round-robin proxy: each replica sees every image."""
    rng = np.random.default_rng(6)
    table = _table(rng)
    images = _scenes(rng, 0, 20, blur=1.0, frames=1)
    alone = DriftMonitor(MANIFEST, lambda: (1, table), SEQUENTIAL)
    fleet = Fleet(f"sqlite://{tmp_path}/data/calibration.db", 3, table, stack)
    cycles = images * 6
    for request in cycles:
        _record(alone, request)
    fleet.send(cycles)
    reports = fleet.settle()
    expected = alone.report()
    assert expected.sequential.looks == 20
    _agree(reports, expected, replicas=3)
    assert sum(replica.looks.shape[0] for replica in fleet.shared()) == 3 * 20


def _replica(name: str, frames: list[tuple[float, Frame]], looks: list[float], **fields) -> ReplicaLooks:
    return ReplicaLooks(
        replica=name,
        covered_until=fields.get("covered_until", 100.0),
        complete_since=fields.get("complete_since", 0.0),
        frame_times=np.array([seen for seen, _ in frames]),
        frames=tuple(frame for _, frame in frames),
        looks=np.array([[seen, 0.0] for seen in looks]).reshape(-1, 2),
        statuses=np.full(len(looks), np.nan),
        keys=np.arange(1, len(looks) + 1, dtype=np.int64) + 1000 * ord(name),
    )


def test_a_look_whose_neighbouring_frames_were_dropped_does_not_count() -> None:
    scene = [_frame(("duck", 100 + k, 50)) for k in range(3)]
    a = _replica("a", [(1.0, scene[0]), (3.0, scene[2])], [1.0])
    b = _replica("b", [(2.0, scene[1])], [2.0])
    assert [s.tolist() for s in fleet_statuses([a, b])] == [[COUNTED], [CONTINUED]]
    elsewhere = _replica("b", [(2.0, _frame(("duck", 400, 300)))], [2.0])
    assert [s.tolist() for s in fleet_statuses([a, elsewhere])] == [[COUNTED], [COUNTED]]
    dropped = _replica("b", [(2.0, _frame(("duck", 400, 300)))], [2.0], complete_since=1.5)
    # b dropped its frames until 1.5: which frames preceded either look is unknown, neither counts
    assert [s.tolist() for s in fleet_statuses([a, dropped])] == [[CONTINUED], [CONTINUED]]
    alone = _replica("a", [(1.0, scene[0])], [1.0], complete_since=0.5)
    assert [s.tolist() for s in fleet_statuses([alone])] == [[COUNTED]]  # nothing to continue


def test_a_look_is_settled_once_every_replica_shared_its_frames_up_to_it() -> None:
    a = _replica("a", [(1.0, _frame(("duck", 0, 0))), (5.0, _frame(("mug", 300, 0)))], [1.0, 5.0])
    behind = _replica("b", [(0.5, _frame(("lego", 600, 0)))], [0.5], covered_until=3.0)
    assert settle(a, [behind], read_at=10.0).tolist()[0] == COUNTED
    assert np.isnan(settle(a, [behind], read_at=10.0)[1])  # b may have frames between 3.0 and 5.0
    assert settle(a, [], read_at=4.0).tolist()[0] == COUNTED  # a replica started after 4.0 saw none
    assert np.isnan(settle(a, [], read_at=4.0)[1])


def test_a_restart_with_the_same_pid_continues_the_windows_and_looks(
    tmp_path: Path, stack: ExitStack
) -> None:
    """A restarted container's server has its predecessor's pid (1): its row is still taken over,
    and a scene that goes on across the restart stays one look."""
    rng = np.random.default_rng(7)
    table = _table(rng)
    url = f"sqlite://{tmp_path}/data/calibration.db"

    def server() -> DriftMonitor:  # named host:pid, like every server process: the same here
        return DriftMonitor(
            MANIFEST, lambda: (1, table), SEQUENTIAL, DriftShares(open_store(url), MODEL, INTERVAL)
        )

    before = server()
    before.start()
    for request in _scenes(rng, 0, 10, blur=1.0):
        _record(before, request)
    before.stop()  # writes its row once more
    seen = before.report()
    after = server()
    after.start()
    stack.callback(after.stop)
    continued = after.report()
    assert seen.sequential.looks == 10 and seen.sequential.frames == 60
    assert (continued.sequential.looks, continued.sequential.frames) == (10, 60), continued.sequential
    assert continued.recorded == seen.recorded > 0
    scene = _scenes(rng, 9, 1, blur=1.0)[1:]  # the last scene goes on: not a new look
    for request in scene:
        _record(after, request)
    assert after.report().sequential.looks == 10


def test_a_row_written_before_looks_were_merged_still_counts_its_looks() -> None:
    """A server upgraded in place takes over its predecessor's row: the older payload decodes."""
    buffer = io.BytesIO()
    meta = json.dumps({"version": 1, "frames": 3, "recorded": 8}).encode()
    window = np.zeros((2, 7), dtype=np.float32)
    np.savez(
        buffer,
        meta=np.frombuffer(meta, dtype=np.uint8),
        windows=window,
        counts=np.array([2]),
        look_windows=window,
        look_counts=np.array([2]),
        looks=np.array([[10.0, 0.5], [11.0, -0.2]]),
    )
    share = decode_share("host:7", 12.0, buffer.getvalue())
    assert (share.version, share.frames, share.recorded) == (1, 3, 8)
    assert share.seen.frames == () and share.seen.covered_until == 12.0
    newer = _replica("b", [(10.5, _frame(("duck", 0, 0)))], [10.5])
    statuses = fleet_statuses([share.seen, newer])
    assert statuses[0].tolist() == [COUNTED, COUNTED] and statuses[1].tolist() == [COUNTED]
