"""A real ``keypoint-service serve`` subprocess on loopback, and its resident memory."""

from __future__ import annotations

import os
import signal
import socket
import subprocess
import sys
import tempfile
import time
import urllib.request
from collections.abc import Iterator
from contextlib import contextmanager, suppress
from dataclasses import dataclass
from pathlib import Path


def free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


@dataclass(frozen=True)
class Server:
    """A running server: its base URL and the pid of the ``serve`` process."""

    url: str
    pid: int

    def rss_kib(self) -> int:
        """VmRSS of the ``serve`` process and all its descendants (the workers when CKS_WORKERS > 1)."""
        return sum(_rss_kib(pid) for pid in _process_tree(self.pid))

    def cpu_seconds(self) -> float:
        """User + system CPU seconds of the server process and its descendants so far (those that
        exited are not counted: measure differences over a run of a server that keeps its processes)."""
        return sum(_cpu_seconds(pid) for pid in _process_tree(self.pid))


def _process_tree(pid: int) -> list[int]:
    """``pid`` and its descendants, by parent pid (a process that exits meanwhile is left out)."""
    parents: dict[int, list[int]] = {}
    for stat in Path("/proc").glob("[0-9]*/stat"):
        try:
            fields = stat.read_text().rpartition(")")[2].split()
        except OSError:
            continue
        parents.setdefault(int(fields[1]), []).append(int(stat.parent.name))
    tree, frontier = [pid], [pid]
    while frontier:
        frontier = [child for parent in frontier for child in parents.get(parent, [])]
        tree += frontier
    return tree


def _cpu_seconds(pid: int) -> float:
    try:
        fields = Path(f"/proc/{pid}/stat").read_text().rpartition(")")[2].split()
    except OSError:
        return 0.0
    return (int(fields[11]) + int(fields[12])) / os.sysconf("SC_CLK_TCK")  # utime, stime


def _rss_kib(pid: int) -> int:
    """VmRSS of a process; 0 once it has exited (or is a zombie without memory)."""
    try:
        lines = Path(f"/proc/{pid}/status").read_text().splitlines()
    except OSError:
        return 0
    return next((int(line.split()[1]) for line in lines if line.startswith("VmRSS:")), 0)


def _wait_ready(url: str, process: subprocess.Popen, timeout: float) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if process.poll() is not None:
            raise RuntimeError(f"the server exited with code {process.returncode} before it was ready")
        try:
            with urllib.request.urlopen(url, timeout=2) as response:
                if response.status == 200:
                    return
        except OSError:
            time.sleep(0.2)
    raise RuntimeError(f"the server at {url} was not ready within {timeout:.0f} s")


@contextmanager
def launch(
    argv: list[str], env: dict[str, str], port: int, log: Path | None = None, timeout: float = 120
) -> Iterator[Server]:
    """Run ``argv`` (a server listening on ``port``) until its ``/readyz`` answers 200; stop it on exit."""
    output = open(log or os.devnull, "ab")  # noqa: SIM115 - closed below
    process = subprocess.Popen(argv, env=env, stdout=output, stderr=output, start_new_session=True)
    try:
        url = f"http://127.0.0.1:{port}"
        _wait_ready(f"{url}/readyz", process, timeout)
        yield Server(url, process.pid)
    finally:
        _stop(process)
        output.close()


def _stop(process: subprocess.Popen) -> None:
    """SIGINT to the server's process group (its workers too); SIGKILL for what is left after 30 s."""
    with suppress(ProcessLookupError):
        os.killpg(process.pid, signal.SIGINT)
    with suppress(subprocess.TimeoutExpired):
        process.wait(timeout=30)
    with suppress(ProcessLookupError):  # workers that outlive their parent belong to the group
        os.killpg(process.pid, signal.SIGKILL)
    process.wait()


@contextmanager
def serve(settings: dict[str, str], log: Path | None = None, timeout: float = 120) -> Iterator[Server]:
    """Start ``python -m service.cli serve`` with ``CKS_*`` settings; stop it on exit."""
    port = free_port()
    with tempfile.TemporaryDirectory(prefix="cks-bench-") as data_dir:
        env = {**os.environ, "CKS_DATA_DIR": data_dir, "CKS_PORT": str(port), **settings}
        argv = [sys.executable, "-m", "service.cli", "serve"]
        with launch(argv, env, port, log, timeout) as server:
            yield server
