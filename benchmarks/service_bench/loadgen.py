"""wrk as the load generator: one prebuilt request body posted over keep-alive connections."""

from __future__ import annotations

import re
import resource
import shutil
import signal
import subprocess
import tempfile
from dataclasses import dataclass
from pathlib import Path

INSTALL_HINT = "apt-get install -y wrk"
DONE_MARKER = "cks-bench: enough responses"

_UNITS = {"us": 1e-3, "ms": 1.0, "s": 1e3, "m": 60e3}
_SCRIPT = """\
wrk.method = "POST"
local file = assert(io.open("{body}", "rb"))
wrk.body = file:read("*a")
file:close()
wrk.headers["Content-Type"] = "{content_type}"
wrk.headers["Accept"] = "application/json"
"""
_STOP_AFTER = """\
local done = 0
function response(status, headers, body)
  done = done + 1
  if done == {limit} then
    io.write("{marker}\\n")
    io.flush()
    wrk.thread:stop()
  end
end
"""


@dataclass(frozen=True)
class LoadResult:
    """What wrk measured for one (body, concurrency) point."""

    concurrency: int
    requests: int
    seconds: float
    requests_per_s: float
    p50_ms: float
    p99_ms: float
    errors: int  # non-2xx responses plus socket errors
    loadgen_cpu_share: float  # wrk CPU seconds / wall seconds (fraction of one core)


def require_wrk() -> str:
    """Path of wrk, or exit with the install command."""
    path = shutil.which("wrk")
    if path is None:
        raise SystemExit(f"wrk (the load generator) is not installed; install it with: {INSTALL_HINT}")
    return path


def write_script(directory: Path, body: bytes, content_type: str, stop_after: int | None = None) -> Path:
    """A wrk Lua script posting ``body``; with ``stop_after``, wrk stops after that many responses."""
    body_path = directory / "body.bin"
    body_path.write_bytes(body)
    text = _SCRIPT.format(body=body_path, content_type=content_type)
    if stop_after:
        text += _STOP_AFTER.format(limit=stop_after, marker=DONE_MARKER)
    script = directory / "post.lua"
    script.write_text(text)
    return script


def _duration_ms(text: str) -> float:
    match = re.fullmatch(r"([\d.]+)(us|ms|s|m)", text)
    if not match:
        raise ValueError(f"cannot read wrk duration {text!r}")
    return float(match[1]) * _UNITS[match[2]]


def parse_wrk(output: str, concurrency: int, cpu_seconds: float) -> LoadResult:
    """Read requests, duration, requests/s, p50, p99 and errors from ``wrk --latency`` output."""
    total = re.search(r"(\d+) requests in ([\d.]+)(us|ms|s|m)", output)
    rate = re.search(r"Requests/sec:\s+([\d.]+)", output)
    p50 = re.search(r"^\s+50%\s+(\S+)", output, re.MULTILINE)
    p99 = re.search(r"^\s+99%\s+(\S+)", output, re.MULTILINE)
    if not (total and rate and p50 and p99):
        raise RuntimeError(f"unexpected wrk output:\n{output}")
    errors = re.search(r"Non-2xx or 3xx responses: (\d+)", output)
    socket_errors = re.search(r"Socket errors: connect (\d+), read (\d+), write (\d+), timeout (\d+)", output)
    seconds = _duration_ms(total[2] + total[3]) / 1e3
    return LoadResult(
        concurrency=concurrency,
        requests=int(total[1]),
        seconds=seconds,
        requests_per_s=float(rate[1]),
        p50_ms=_duration_ms(p50[1]),
        p99_ms=_duration_ms(p99[1]),
        errors=(int(errors[1]) if errors else 0)
        + (sum(map(int, socket_errors.groups())) if socket_errors else 0),
        loadgen_cpu_share=cpu_seconds / seconds if seconds else 0.0,
    )


def _children_cpu() -> float:
    usage = resource.getrusage(resource.RUSAGE_CHILDREN)
    return usage.ru_utime + usage.ru_stime


def _wrk_command(url: str, script: Path, concurrency: int, seconds: float) -> list[str]:
    return [
        require_wrk(),
        "-t1",
        f"-c{concurrency}",
        f"-d{max(1, round(seconds))}s",
        "--latency",
        "--timeout",
        "60s",
        "-s",
        str(script),
        f"{url}/v1/predict",
    ]


def run_wrk(url: str, script: Path, concurrency: int, seconds: float) -> LoadResult:
    """One closed-loop wrk run: ``concurrency`` connections on one wrk thread for ``seconds``."""
    before = _children_cpu()
    command = _wrk_command(url, script, concurrency, seconds)
    output = subprocess.run(command, check=True, capture_output=True, text=True).stdout
    return parse_wrk(output, concurrency, _children_cpu() - before)


def post_requests(url: str, body: bytes, content_type: str, count: int, concurrency: int) -> LoadResult:
    """Send ``count`` requests: the script stops wrk's thread and says so, then wrk gets SIGINT.

    (wrk's main thread sleeps for the whole ``-d``; SIGINT ends that sleep and it reports.)
    """
    with tempfile.TemporaryDirectory(prefix="cks-wrk-") as directory:
        script = write_script(Path(directory), body, content_type, stop_after=count)
        before = _children_cpu()
        command = _wrk_command(url, script, concurrency, 24 * 3600)
        with subprocess.Popen(command, stdout=subprocess.PIPE, text=True) as wrk:
            assert wrk.stdout is not None
            for line in wrk.stdout:
                if line.strip() == DONE_MARKER:
                    wrk.send_signal(signal.SIGINT)
                    break
            output = wrk.stdout.read()
        if wrk.returncode != 0:
            raise RuntimeError(f"wrk failed with code {wrk.returncode}:\n{output}")
        return parse_wrk(output, concurrency, _children_cpu() - before)
