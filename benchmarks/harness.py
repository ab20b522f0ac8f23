"""What every benchmark shares: the request, a real server (the service or a peer) on loopback,
wrk's timing of it, the machine the figures come from, and the sections of docs/performance.md.

docs/performance.md is written by three commands, each owning one marked section, so that any of
them can be rerun alone: ``bench_peers`` (with ``--gpu``, ``bench_peers_gpu``), ``bench_frames``
and ``bench_service``.
"""

from __future__ import annotations

import json
import os
import platform
import re
import resource
import shutil
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

import numpy as np
import onnxruntime

from service.infra.settings import DEFAULT_MODEL_DIR

ROOT = Path(__file__).resolve().parents[1]
PERFORMANCE_PAGE = ROOT / "docs" / "performance.md"
BOXES = (1, 4)  # boxes per request: the README's request, and a busier one
BOUNDARY = "----cks-bench-boundary"


def log(message: str) -> None:
    print(message, flush=True)


# ---------------------------------------------------------------- the request


@dataclass(frozen=True)
class Sample:
    """One image file and the instances sent with it."""

    name: str
    jpeg: bytes
    objects: tuple[str, ...]
    boxes: np.ndarray  # (N, 4) x, y, w, h

    @property
    def instances(self) -> list[dict]:
        return [
            {"object": obj, "bbox": [float(v) for v in box]}
            for obj, box in zip(self.objects, self.boxes, strict=True)
        ]

    def with_instances(self, count: int) -> Sample:
        """The first ``count`` instances (repeated if the image has fewer)."""
        index = np.arange(count) % len(self.objects)
        return Sample(self.name, self.jpeg, tuple(self.objects[i] for i in index), self.boxes[index])

    def parameters_json(self) -> str:
        return json.dumps({"instances": self.instances})

    def multipart_body(self) -> tuple[bytes, str]:
        """``(body, content type)`` of a multipart/form-data predict request."""
        head = (
            f'--{BOUNDARY}\r\nContent-Disposition: form-data; name="image"; filename="{self.name}"\r\n'
            "Content-Type: image/jpeg\r\n\r\n"
        ).encode()
        request = (
            f'\r\n--{BOUNDARY}\r\nContent-Disposition: form-data; name="request"\r\n'
            f"Content-Type: application/json\r\n\r\n{self.parameters_json()}\r\n--{BOUNDARY}--\r\n"
        ).encode()
        return head + self.jpeg + request, f"multipart/form-data; boundary={BOUNDARY}"


def load_sample(samples_dir: Path = DEFAULT_MODEL_DIR / "samples") -> Sample:
    """The image of a COCO samples folder with the most annotated instances (the README's)."""
    coco = json.loads((samples_dir / "annotations.json").read_text())
    categories = {c["id"]: c["name"] for c in coco["categories"]}
    by_image: dict[int, list[dict]] = {}
    for annotation in coco["annotations"]:
        by_image.setdefault(annotation["image_id"], []).append(annotation)
    image_id = max(by_image, key=lambda i: (len(by_image[i]), -i))
    image = next(i for i in coco["images"] if i["id"] == image_id)
    annotations = by_image[image_id]
    return Sample(
        name=image["file_name"].rsplit("/", 1)[-1],
        jpeg=(samples_dir / image["file_name"]).read_bytes(),
        objects=tuple(categories[a["category_id"]] for a in annotations),
        boxes=np.array([a["bbox"] for a in annotations], dtype=np.float64),
    )


@dataclass(frozen=True)
class Requests:
    """The sample with each of ``BOXES`` boxes: multipart bodies and the wrk scripts posting them."""

    bodies: dict[int, tuple[bytes, str]]
    scripts: dict[int, Path]

    @staticmethod
    def write(directory: Path, sample: Sample) -> Requests:
        bodies, scripts = {}, {}
        for boxes in BOXES:
            bodies[boxes] = sample.with_instances(boxes).multipart_body()
            folder = directory / f"boxes-{boxes}"
            folder.mkdir()
            scripts[boxes] = write_script(folder, *bodies[boxes])
        return Requests(bodies, scripts)


# ---------------------------------------------------------------- a server


def free_port() -> int:
    with socket.socket() as probe:
        probe.bind(("127.0.0.1", 0))
        return probe.getsockname()[1]


@dataclass(frozen=True)
class Server:
    """A running server: its base URL and the pid of its first process."""

    url: str
    pid: int

    def rss_kib(self) -> int:
        """VmRSS of the server's process and all its descendants (workers, when there are)."""
        return sum(_status_kib(pid, "VmRSS") for pid in _process_tree(self.pid))

    def cpu_seconds(self) -> float:
        """User + system CPU seconds of the server's processes so far (those that exited are not
        counted: measure differences over a run of a server that keeps its processes)."""
        return sum(_cpu_seconds(pid) for pid in _process_tree(self.pid))


def _process_tree(pid: int) -> list[int]:
    """``pid`` and its descendants, by parent pid (a process that exits meanwhile is left out)."""
    parents: dict[int, list[int]] = {}
    for stat in Path("/proc").glob("[0-9]*/stat"):
        with suppress(OSError):
            parents.setdefault(int(stat.read_text().rpartition(")")[2].split()[1]), []).append(
                int(stat.parent.name)
            )
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


def _status_kib(pid: int, field: str) -> int:
    """A kB field of /proc/<pid>/status; 0 once the process has exited."""
    try:
        lines = Path(f"/proc/{pid}/status").read_text().splitlines()
    except OSError:
        return 0
    return next((int(line.split()[1]) for line in lines if line.startswith(f"{field}:")), 0)


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
    """This checkout's ``python -m service.cli serve`` with ``CKS_*`` ``settings`` over the
    environment's, in a data directory of its own; stopped on exit."""
    port = free_port()
    with tempfile.TemporaryDirectory(prefix="cks-bench-") as data_dir:
        env = {**os.environ, "CKS_DATA_DIR": data_dir, "CKS_PORT": str(port), **settings}
        with launch([sys.executable, "-m", "service.cli", "serve"], env, port, log, timeout) as server:
            yield server


# ---------------------------------------------------------------- timing (wrk)

_UNITS = {"us": 1e-3, "ms": 1.0, "s": 1e3, "m": 60e3}
_SCRIPT = """\
wrk.method = "POST"
local file = assert(io.open("{body}", "rb"))
wrk.body = file:read("*a")
file:close()
wrk.headers["Content-Type"] = "{content_type}"
wrk.headers["Accept"] = "application/json"
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
        raise SystemExit("wrk (the load generator) is not installed; install it with: apt-get install -y wrk")
    return path


def write_script(directory: Path, body: bytes, content_type: str) -> Path:
    """A wrk Lua script posting ``body`` to whatever URL wrk is given."""
    body_path = directory / "body.bin"
    body_path.write_bytes(body)
    script = directory / "post.lua"
    script.write_text(_SCRIPT.format(body=body_path, content_type=content_type))
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


def run_wrk(url: str, script: Path, concurrency: int, seconds: float) -> LoadResult:
    """One closed-loop run on ``url``/v1/predict: ``concurrency`` keep-alive connections on one wrk
    thread for ``seconds``."""
    before = _children_cpu()
    command = [require_wrk(), "-t1", f"-c{concurrency}", f"-d{max(1, round(seconds))}s", "--latency"]
    command += ["--timeout", "60s", "-s", str(script), f"{url}/v1/predict"]
    output = subprocess.run(command, check=True, capture_output=True, text=True).stdout
    return parse_wrk(output, concurrency, _children_cpu() - before)


# ---------------------------------------------------------------- the machine


@dataclass(frozen=True)
class Machine:
    cpus: int
    cpu_model: str
    load_at_start: tuple[float, float, float]
    python: str
    onnxruntime: str

    def describe(self) -> str:
        load = ", ".join(f"{value:.2f}" for value in self.load_at_start)
        return (
            f"{self.cpus} CPUs ({self.cpu_model}); load average at start {load} (1, 5, 15 min); "
            f"Python {self.python}, onnxruntime {self.onnxruntime}"
        )


def this_machine() -> Machine:
    model = next(
        (
            line.split(":", 1)[1].strip()
            for line in Path("/proc/cpuinfo").read_text().splitlines()
            if line.startswith("model name")
        ),
        platform.processor() or "unknown",
    )
    cpus = len(os.sched_getaffinity(0))
    return Machine(cpus, model, os.getloadavg(), platform.python_version(), onnxruntime.__version__)


def load_average() -> str:
    return ", ".join(f"{v:.2f}" for v in os.getloadavg())


# ---------------------------------------------------------------- docs/performance.md

SECTIONS = ("bench_peers", "bench_peers_gpu", "bench_frames", "bench_service", "variant_trade")
INTRO = (
    "Four commands write this page, each its own section: `python -m benchmarks.bench_peers` (the service"
    " against the frameworks a user would pick instead, ratios first; with `--gpu`, its own section for"
    " the model on a GPU), `python -m benchmarks.bench_frames` (a camera frame in memory to sets: regions"
    " and raw pixels against the whole JPEG) and `python -m benchmarks.bench_service` (the service against"
    " its bare model: stage breakdown, memory); `python -m benchmarks.variant_trade` (what the int8 variant"
    " trades: coverage, accuracy, set sizes, the model's run). Do not edit by hand."
)


def _marker(name: str, end: bool = False) -> str:
    return f"<!-- {name}:{'end' if end else 'begin'} -->"


def write_section(path: Path, name: str, text: str) -> None:
    """Replace section ``name`` (one of ``SECTIONS``) of the page at ``path`` (created if missing)."""
    page = path.read_text() if path.exists() else ""
    sections = {}
    for section in SECTIONS:
        pattern = re.escape(_marker(section)) + r"(.*?)" + re.escape(_marker(section, True))
        if match := re.search(pattern, page, re.S):
            sections[section] = match[1].strip()
    sections[name] = text.strip()
    parts = ["# Performance", INTRO]
    parts += [f"{_marker(n)}\n{sections[n]}\n{_marker(n, True)}" for n in SECTIONS if n in sections]
    path.parent.mkdir(parents=True, exist_ok=True)
    path.write_text("\n\n".join(parts) + "\n")
