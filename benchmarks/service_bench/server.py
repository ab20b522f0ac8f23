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
from contextlib import contextmanager
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


def _process_tree(pid: int) -> list[int]:
    children = []
    for task in Path(f"/proc/{pid}/task").iterdir():
        children += [int(child) for child in (task / "children").read_text().split()]
    return [pid] + [descendant for child in children for descendant in _process_tree(child)]


def _rss_kib(pid: int) -> int:
    for line in Path(f"/proc/{pid}/status").read_text().splitlines():
        if line.startswith("VmRSS:"):
            return int(line.split()[1])
    raise RuntimeError(f"no VmRSS for pid {pid}")


def _wait_ready(url: str, process: subprocess.Popen, timeout: float) -> None:
    deadline = time.monotonic() + timeout
    while time.monotonic() < deadline:
        if process.poll() is not None:
            raise RuntimeError(f"the server exited with code {process.returncode} before it was ready")
        try:
            with urllib.request.urlopen(f"{url}/readyz", timeout=2) as response:
                if response.status == 200:
                    return
        except OSError:
            time.sleep(0.2)
    raise RuntimeError(f"the server at {url} was not ready within {timeout:.0f} s")


@contextmanager
def serve(settings: dict[str, str], log: Path | None = None, timeout: float = 120) -> Iterator[Server]:
    """Start ``python -m service.cli serve`` with ``CKS_*`` settings; stop it on exit."""
    command = ["-m", "service.cli", "serve"]
    port = free_port()
    with tempfile.TemporaryDirectory(prefix="cks-bench-") as data_dir:
        env = {**os.environ, "CKS_DATA_DIR": data_dir, "CKS_PORT": str(port), **settings}
        output = open(log or os.devnull, "ab")  # noqa: SIM115 - closed below
        process = subprocess.Popen([sys.executable, *command], env=env, stdout=output, stderr=output)
        try:
            url = f"http://127.0.0.1:{port}"
            _wait_ready(url, process, timeout)
            yield Server(url, process.pid)
        finally:
            process.send_signal(signal.SIGINT)
            try:
                process.wait(timeout=30)
            except subprocess.TimeoutExpired:
                process.kill()
                process.wait()
            output.close()
