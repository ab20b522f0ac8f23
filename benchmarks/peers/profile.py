"""Where the service's CPU goes under load: py-spy samples of the server during a wrk run, by stage.

py-spy (``pip install py-spy``, in the ``peers`` extra) samples every thread of the server
process and of its worker processes (``CKS_WORKERS``); samples are sorted into the request's
stages by the innermost frame that names one (``STAGES``, first match from the top of the
table), and waits (a thread blocked on a lock, a queue or the event loop's selector) are left
out, so the shares are of the time threads were running.
"""

from __future__ import annotations

import collections
import shutil
import subprocess
import tempfile
from dataclasses import dataclass
from pathlib import Path

from benchmarks.harness import Server, run_wrk

#: (stage, function names that put a sample in it): the first row are waits (innermost frame only);
#: otherwise the innermost frame that names a stage decides, the first row matching it
STAGES = (
    (
        "waiting (locks, queues, selector)",
        (
            "Condition.wait",
            "Event.wait",
            "Future.result",
            "_form_group",
            "_next_group",
            "_worker",
            "Runner.run",
            "EpollSelector.select",
        ),
    ),
    ("inference (onnxruntime)", ("Session.run", "InferenceSession.run")),
    ("decode (JPEG)", ("decode_image",)),
    ("crop + normalize", ("build_batch",)),
    ("sets (calibrated_sets)", ("calibrated_sets",)),
    ("response data + JSON", ("predict", "predict_response", "predict_json", "model_dump_json", "_respond")),
    ("multipart parsing", ("MultiPartParser", "MultipartParser", "Request.form", "_parse_multipart")),
    ("validation (pydantic)", ("model_validate_json", "_validated")),
    ("body reading", ("read_limited_body", "receive")),
)
OTHER = "HTTP, routing, middleware, event loop"


@dataclass(frozen=True)
class Profile:
    samples: int
    running: int  # samples outside waits
    shares: dict[str, float]  # stage -> share of running samples
    problem: str | None = None


def _names_one_of(frame: str, names: tuple[str, ...]) -> bool:
    function = frame.split(" (")[0]  # "Class.method (file.py:line)"
    return any(function == name or name in function.split(".") for name in names)


def _stage(frames: list[str]) -> str:
    """A thread waits when its innermost frame is a wait; else the innermost frame naming a stage."""
    (waiting, waits), *stages = STAGES
    if frames and _names_one_of(frames[-1], waits):
        return waiting
    for frame in reversed(frames):
        for stage, names in stages:
            if _names_one_of(frame, names):
                return stage
    return OTHER


def summarize(raw: str) -> Profile:
    """Shares per stage from py-spy's ``--format raw`` output (``frame;frame;... count`` lines)."""
    counts: collections.Counter[str] = collections.Counter()
    for line in raw.splitlines():
        stack, _, count = line.rpartition(" ")
        if stack and count.isdigit():
            counts[_stage(stack.split(";")[1:])] += int(count)
    samples = sum(counts.values())
    waiting = counts.pop(STAGES[0][0], 0)
    running = samples - waiting
    shares = {stage: n / running for stage, n in counts.most_common()} if running else {}
    return Profile(samples, running, shares)


def profile_under_load(server: Server, script: Path, concurrency: int, seconds: float) -> Profile:
    """py-spy on the server while wrk runs ``concurrency`` connections for ``seconds``."""
    spy = shutil.which("py-spy")
    if spy is None:
        return Profile(0, 0, {}, "py-spy is not installed (pip install py-spy)")
    with tempfile.TemporaryDirectory(prefix="cks-spy-") as directory:
        output = Path(directory) / "raw.txt"
        command = [
            spy,
            "record",
            "-p",
            str(server.pid),
            "-d",
            str(max(1, round(seconds))),
            "-r",
            "100",
            "--nonblocking",
            "--threads",
            "--subprocesses",
            "-f",
            "raw",
            "-o",
            str(output),
        ]
        with subprocess.Popen(
            command, stdout=subprocess.DEVNULL, stderr=subprocess.PIPE, text=True
        ) as sampler:
            run_wrk(server.url, script, concurrency, seconds + 1)
            _, errors = sampler.communicate(timeout=60)
        if sampler.returncode != 0 or not output.exists():
            return Profile(
                0, 0, {}, f"py-spy failed: {errors.strip().splitlines()[-1:] or sampler.returncode}"
            )
        return summarize(output.read_text())
