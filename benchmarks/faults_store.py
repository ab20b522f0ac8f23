"""A real server while its calibration store is away, for the live tests (test_store_outage,
test_sqlite_outage, test_jobs_stale, test_shutdown).

``scene`` starts one real server on a throwaway PostgreSQL cluster's database (or on SQLite),
bundled model and calibration, version 1 active, and stores a second version without activating
it. ``run_outage`` has client threads predict continuously with the active version while the
store is away (``fault``: the cluster stopped, frozen with SIGSTOP as a paused VM would be, or a
SQLite store whose WAL locks another process holds) and after it returns, and reports the
predictions answered and failed before, during and after; how admin calls, /readyz and a predict
naming a version not in memory answered meanwhile; and how long the server took to notice, to
recover, and to serve an activation written to the store during recovery (as another replica
would). Every wait is capped at ``WAIT_LIMIT_S``.
"""

from __future__ import annotations

import json
import subprocess
import sys
import threading
import time
from collections.abc import Callable, Iterator
from contextlib import contextmanager
from dataclasses import dataclass, field
from pathlib import Path
from typing import Any

import httpx
import numpy as np

from calibration_store import open_store, sqlite_path
from tests.live.server import LiveServer
from tests.postgres_cluster import PostgresCluster
from tests.predict_client import instances_of, predict_json
from tests.samples import batch_zip, load_samples, model_dir, samples_by_image
from tests.service_calls import ADMIN_TOKEN, wait_until

#: longest any single wait of the scenario may take
WAIT_LIMIT_S = 30.0
ADMIN_PROBE = "/v1/admin/calibrations"


@dataclass(frozen=True)
class Outcome:
    """One predict as a client saw it (status 0: no HTTP answer)."""

    began: float  # time.monotonic()
    seconds: float
    status: int


@dataclass(frozen=True)
class PhaseFigures:
    answered: int
    failed: int
    p50_ms: float
    p99_ms: float

    @classmethod
    def of(cls, outcomes: list[Outcome]) -> PhaseFigures:
        ok = [o.seconds * 1e3 for o in outcomes if o.status == 200]
        p50, p99 = np.percentile(ok, [50, 99]) if ok else (float("nan"), float("nan"))
        return cls(len(ok), len(outcomes) - len(ok), float(p50), float(p99))


@dataclass(frozen=True)
class Call:
    """One HTTP exchange: status, seconds, Retry-After and the JSON body (or {})."""

    status: int
    seconds: float
    retry_after: str | None
    body: dict

    @classmethod
    def timed(cls, send: Callable[[], httpx.Response]) -> Call:
        began = time.monotonic()
        response = send()
        seconds = time.monotonic() - began
        try:
            body = response.json()
        except ValueError:
            body = {}
        return cls(response.status_code, seconds, response.headers.get("Retry-After"), body)


@dataclass
class OutageReport:
    fault: str  # Fault.name
    outage_s: float
    phases: dict[str, PhaseFigures]  # before, during, after
    admin_first: Call  # sent right after the stop, before the server knew
    admin_known: Call  # sent once /readyz said the store is unreachable
    readyz_during: Call
    named_active: Call  # predict naming the active version (in memory)
    named_other: Call  # predict naming a version not in memory
    unreachable_after_s: float  # stop -> /readyz says unreachable
    recovered_after_s: float  # restart -> /readyz says ok
    activation_seen_after_s: float  # activation written to the store during recovery -> served
    admin_ok_after_s: float  # restart -> an admin call answers 200


@dataclass
class PredictLoad:
    """Client threads predicting back to back (``pause`` seconds apart) until stopped."""

    url: str
    image: bytes
    parameters: dict[str, Any]
    clients: int = 2
    pause: float = 0.02
    outcomes: list[Outcome] = field(default_factory=list)

    def __post_init__(self) -> None:
        self._stop = threading.Event()
        self._threads = [threading.Thread(target=self._run, daemon=True) for _ in range(self.clients)]

    def start(self) -> None:
        for thread in self._threads:
            thread.start()

    def stop(self) -> list[Outcome]:
        self._stop.set()
        for thread in self._threads:
            thread.join(timeout=WAIT_LIMIT_S)
        return sorted(self.outcomes, key=lambda o: o.began)

    def _run(self) -> None:
        with httpx.Client(base_url=self.url, timeout=30.0) as client:
            while not self._stop.is_set():
                began = time.monotonic()
                try:
                    status = predict_json(client, self.image, self.parameters).status_code
                except httpx.HTTPError:
                    status = 0
                self.outcomes.append(Outcome(began, time.monotonic() - began, status))  # list.append: atomic
                self._stop.wait(self.pause)


@dataclass(frozen=True)
class Scene:
    """A server on a cluster's database (or on SQLite: no cluster), version 1 active and version 2
    stored (not in memory)."""

    cluster: PostgresCluster | None
    store_url: str
    server: LiveServer
    image: bytes
    parameters: dict[str, Any]


@contextmanager
def scene(work: Path, cluster: PostgresCluster | None, **settings: Any) -> Iterator[Scene]:
    """Start a server with ``settings`` on a new database of ``cluster`` (None: on its SQLite
    file), and store version 2."""
    samples_dir = model_dir() / "samples"
    coco = json.loads((samples_dir / "annotations.json").read_text())
    path, group = next(iter(samples_by_image(load_samples(samples_dir, coco)).items()))
    url = cluster.create_database() if cluster else f"sqlite:///{work / 'data' / 'calibrations.db'}"
    with LiveServer(work / "data", admin_token=ADMIN_TOKEN, store_url=url, **settings) as server:
        job = server.calibrate(batch_zip(samples_dir, coco, images=4))
        assert job["result"]["version"] == 2, job
        yield Scene(cluster, url, server, path.read_bytes(), {"instances": instances_of(group)})


def seconds_until(condition: Callable[[], bool], what: str) -> float:
    """Seconds until ``condition()`` holds (AssertionError naming ``what`` past WAIT_LIMIT_S)."""
    began = time.monotonic()
    wait_until(condition, what, WAIT_LIMIT_S)
    return time.monotonic() - began


class WalLocks:
    """Another process holding every WAL lock of a SQLite database (write, checkpoint, recovery
    and the five read locks: bytes 120 to 127 of its -shm file), as one stuck in a checkpoint or
    a recovery would: the service's readers and writers wait on them, then fail. With
    ``WRITE_LOCK`` alone, as another writer would: writers wait, readers go on."""

    EVERY_LOCK, WRITE_LOCK = range(120, 128), range(120, 121)
    HOLD = (
        "import fcntl, os, sys, time\n"
        "fd = os.open(sys.argv[1], os.O_RDWR)\n"
        "for offset in range(int(sys.argv[2]), int(sys.argv[3])):\n"
        "    fcntl.lockf(fd, fcntl.LOCK_EX | fcntl.LOCK_NB, 1, offset)\n"
        "print('held', flush=True)\n"
        "time.sleep(3600)\n"
    )

    def __init__(self, database: Path, offsets: range = EVERY_LOCK) -> None:
        self._shm, self._offsets, self._process = f"{database}-shm", offsets, None

    def take(self) -> None:
        argv = [sys.executable, "-c", self.HOLD, self._shm, str(self._offsets.start), str(self._offsets.stop)]
        self._process = subprocess.Popen(argv, stdout=subprocess.PIPE, text=True)
        assert self._process.stdout is not None and self._process.stdout.readline().strip() == "held"

    def release(self) -> None:
        if self._process is not None:
            self._process.kill()
            self._process.wait()


@dataclass(frozen=True)
class Fault:
    """What happens to the store: its name, how it begins and how it ends."""

    name: str
    begin: Callable[[], None]
    end: Callable[[], None]

    @classmethod
    def of(cls, kind: str, prepared: Scene) -> Fault:
        if kind == "sqlite-locked":
            locks = WalLocks(sqlite_path(prepared.store_url))
            return cls("SQLite locked (another process holds its WAL locks)", locks.take, locks.release)
        cluster = prepared.cluster
        assert cluster is not None, f"{kind}: a PostgreSQL fault needs a cluster"
        if kind == "freeze":
            return cls("PostgreSQL frozen (SIGSTOP)", cluster.freeze_server, cluster.thaw_server)
        return cls("PostgreSQL stopped", cluster.stop_server, cluster.start_server)


def run_outage(
    prepared: Scene,
    outage_s: float,
    before_s: float = 3.0,
    after_s: float = 5.0,
    clients: int = 2,
    fault: str = "stop",
) -> OutageReport:
    """Predict under load while the store is away (``fault``: "stop", "freeze" or "sqlite-locked")
    for ``outage_s`` seconds, and after it returns."""
    server, client, happens = prepared.server, prepared.server.client, Fault.of(fault, prepared)
    readyz: dict[str, Call] = {}

    def readyz_says(key: str, value: object) -> bool:
        readyz["last"] = Call.timed(lambda: client.get("/readyz"))
        return readyz["last"].body.get(key) == value

    def admin() -> Call:
        return Call.timed(lambda: client.get(ADMIN_PROBE, headers=server.admin))

    def predict_named(version: int) -> Call:
        parameters = {**prepared.parameters, "calibration_version": version}
        return Call.timed(lambda: predict_json(client, prepared.image, parameters))

    load = PredictLoad(server.url, prepared.image, prepared.parameters, clients)
    load.start()
    try:
        time.sleep(before_s)
        stopped_at = time.monotonic()
        happens.begin()
        try:
            admin_first = admin()
            unreachable_after_s = (
                time.monotonic()
                - stopped_at
                + seconds_until(
                    lambda: readyz_says("store", "unreachable"), "/readyz reports the store unreachable"
                )
            )
            readyz_during = readyz["last"]
            admin_known, named_active, named_other = admin(), predict_named(1), predict_named(2)
            time.sleep(max(0.0, stopped_at + outage_s - time.monotonic()))
        finally:
            restarted_at = time.monotonic()
            happens.end()
        with open_store(prepared.store_url) as store:  # another replica's activation, during recovery
            store.activate(readyz_during.body["model_hash"], 2, "faults_store", "activated during recovery")
        activated_at = time.monotonic()
        recovered_after_s = (
            time.monotonic()
            - restarted_at
            + seconds_until(lambda: readyz_says("store", "ok"), "/readyz reports the store ok")
        )
        admin_ok_after_s = (
            time.monotonic()
            - restarted_at
            + seconds_until(lambda: admin().status == 200, "admin calls answer 200")
        )
        activation_seen_after_s = (
            time.monotonic()
            - activated_at
            + seconds_until(lambda: readyz_says("active_calibration", 2), "the activation is served")
        )
        time.sleep(after_s)
    finally:
        outcomes = load.stop()

    def between(start: float, end: float) -> PhaseFigures:
        return PhaseFigures.of([o for o in outcomes if start <= o.began < end])

    phases = {
        "before": between(-np.inf, stopped_at),
        "during": between(stopped_at, restarted_at),
        "after": between(restarted_at, np.inf),
    }
    return OutageReport(
        happens.name,
        outage_s,
        phases,
        admin_first,
        admin_known,
        readyz_during,
        named_active,
        named_other,
        unreachable_after_s,
        recovered_after_s,
        activation_seen_after_s,
        admin_ok_after_s,
    )
