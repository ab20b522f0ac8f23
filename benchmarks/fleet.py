"""A real fleet, for the live test (test_fleet): three replicas behind Debian's HAProxy on one real
PostgreSQL, under steady predict load (docs/deploy.md, "A fleet behind a proxy").

Three ``keypoint-service serve`` processes share a throwaway PostgreSQL cluster; HAProxy
spreads requests over them (round robin, ``/readyz`` checked every 300 ms, a request whose
server failed or vanished retried on another). ``CLIENTS`` threads predict back to back through
the proxy with the Python client, which retries an idempotent call once (``attempts=2``).
Under that load: the replicas' drift answers are read directly from each (they must agree);
version 2 is activated through the proxy and each replica's ``/readyz`` is watched until it
serves it (the spread); replica 2 is SIGKILLed, then replica 3 drained with SIGTERM. Reported:
requests answered and lost per phase, the activation spread, the drift answers. About a minute.
"""

from __future__ import annotations

import json
import shutil
import signal
import subprocess
import threading
import time
from collections import Counter
from collections.abc import Iterator
from contextlib import ExitStack, contextmanager
from dataclasses import dataclass, field
from pathlib import Path

import httpx
from keypoint_client import KeypointClient, RetryPolicy

from benchmarks.load import sample_request
from tests.live.server import LiveServer, free_port
from tests.postgres_cluster import PostgresCluster
from tests.samples import batch_zip, model_dir
from tests.service_calls import ADMIN_TOKEN, wait_until

REPLICAS = 3
CLIENTS = 3
POLL_S = 1.0  # how often a replica reads the store: how soon it serves a new activation
SHARE_S = 5.0  # how often a replica shares its drift windows with the others (the service's interval)
SHIPPED_PROXY = Path(__file__).resolve().parents[1] / "deploy" / "haproxy" / "haproxy.cfg"


def shipped_proxy_config(port: int, servers: list[str]) -> str:
    """deploy/haproxy/haproxy.cfg as shipped, bound to ``port``, in front of ``servers`` (host:port)."""
    lines = SHIPPED_PROXY.read_text().splitlines()
    bind = [i for i, line in enumerate(lines) if line.strip().startswith("bind ")]
    server = [i for i, line in enumerate(lines) if line.strip().startswith("server")]
    assert len(bind) == 1 and len(server) == 1, "the shipped config has one bind and one server line"
    lines[bind[0]] = f"    bind 127.0.0.1:{port}"
    lines[server[0] :] = [f"    server r{n} {address} check" for n, address in enumerate(servers, 1)]
    return "\n".join(lines) + "\n"


@dataclass
class Load:
    """Client threads predicting through the proxy until ``stop``; outcomes per phase."""

    url: str
    phase: str = "steady"
    outcomes: dict[str, Counter] = field(default_factory=dict)
    _stop: threading.Event = field(default_factory=threading.Event)
    _threads: list[threading.Thread] = field(default_factory=list)
    _go: threading.Event | None = None

    def start(self, clients: int) -> None:
        for _ in range(clients):
            thread = threading.Thread(target=self._predict_until_stopped, daemon=True)
            thread.start()
            self._threads.append(thread)

    def pause(self) -> threading.Event:
        """Hold the clients (between requests) until the returned event is set."""
        self._go = threading.Event()
        return self._go

    def stop(self) -> None:
        self._stop.set()
        for thread in self._threads:
            thread.join(timeout=120)

    def _predict_until_stopped(self) -> None:
        image, instances = sample_request()
        boxes = [(i["object"], i["bbox"]) for i in instances]
        with KeypointClient(self.url, timeout=60, retry=RetryPolicy(attempts=2)) as client:
            while not self._stop.is_set():
                if self._go is not None:
                    self._go.wait()
                phase = self.phase
                try:
                    client.predict(image, boxes)
                    outcome = "answered"
                except Exception as error:  # a lost request: said by its type
                    outcome = f"lost ({type(error).__name__}: {str(error)[:80]})"
                self.outcomes.setdefault(phase, Counter())[outcome] += 1


@dataclass
class FleetReport:
    outcomes: dict[str, Counter]
    activation_spread_s: list[float]  # per replica: seconds from the activation's answer to serving it
    drift: list[dict]  # per replica, read directly
    drained_exit: int | None  # the SIGTERMed replica's exit status


def haproxy_binary() -> str | None:
    """Debian's haproxy (in /usr/sbin, which a user's PATH may lack), or None."""
    return shutil.which("haproxy") or next((p for p in ("/usr/sbin/haproxy",) if Path(p).is_file()), None)


@contextmanager
def haproxy(backends: list[str], work: Path) -> Iterator[str]:
    port = free_port()
    config = work / "haproxy.cfg"
    config.write_text(shipped_proxy_config(port, [url.removeprefix("http://") for url in backends]))
    binary = haproxy_binary()
    assert binary, "HAProxy is not installed: apt-get install haproxy (.ci/run does)"
    process = subprocess.Popen([binary, "-f", str(config), "-db"], stderr=subprocess.PIPE, text=True)
    url = f"http://127.0.0.1:{port}"
    try:

        def answers() -> bool:
            assert process.poll() is None, process.stderr.read() if process.stderr else ""
            try:
                return httpx.get(f"{url}/readyz", timeout=2).status_code == 200
            except httpx.TransportError:
                return False

        wait_until(answers, "HAProxy answers", timeout=30)
        yield url
    finally:
        process.terminate()
        process.wait(timeout=10)


def drift_of(url: str) -> dict:
    headers = {"Authorization": f"Bearer {ADMIN_TOKEN}"}
    return httpx.get(f"{url}/v1/admin/drift", headers=headers, timeout=60).json()


def run_fleet(work: Path, cluster: PostgresCluster) -> FleetReport:
    url = cluster.create_database()
    settings = {"admin_token": ADMIN_TOKEN, "store_url": url}
    with ExitStack() as stack:
        replicas = [
            stack.enter_context(LiveServer(work / f"replica{n}", **settings)) for n in range(1, REPLICAS + 1)
        ]
        samples = model_dir() / "samples"
        coco = json.loads((samples / "annotations.json").read_text())
        job = replicas[0].calibrate(batch_zip(samples, coco, images=4))  # version 2, not active yet
        assert job["result"]["version"] == 2, job
        proxy = stack.enter_context(haproxy([r.url for r in replicas], work))
        load = Load(proxy)
        load.start(CLIENTS)
        time.sleep(3)
        for replica in replicas:
            wait_until(lambda r=replica: drift_of(r.url)["replicas"] == REPLICAS, "every replica shares")
        load.phase = "drift read"
        time.sleep(0.5)  # the load moves on to its next phase: the windows stay as they are
        pause_load = load.pause()
        time.sleep(2 * SHARE_S + 1)  # every replica's latest windows written, then read by all
        drift = [drift_of(r.url) for r in replicas]
        pause_load.set()

        load.phase = "activation"
        activation = httpx.post(
            f"{proxy}/v1/admin/calibrations/2/activate",
            json={"reason": "fleet benchmark", "force": True},
            headers={"Authorization": f"Bearer {ADMIN_TOKEN}"},
            timeout=60,
        )
        activated = time.monotonic()
        assert activation.status_code == 200, activation.text
        spread = []
        for replica in replicas:
            wait_until(lambda r=replica: r.client.get("/readyz").json()["active_calibration"] == 2, "served")
            spread.append(time.monotonic() - activated)

        load.phase = "one replica SIGKILLed"
        replicas[1].process.send_signal(signal.SIGKILL)
        time.sleep(3)
        load.phase = "one replica drained (SIGTERM)"
        replicas[2].process.send_signal(signal.SIGTERM)
        drained_exit = replicas[2].process.wait(timeout=60)
        time.sleep(2)
        load.phase = "one replica left"
        time.sleep(2)
        load.stop()
        return FleetReport(load.outcomes, spread, drift, drained_exit)
