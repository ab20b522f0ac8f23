"""What the numbers were measured on."""

from __future__ import annotations

import os
import platform
from dataclasses import dataclass
from pathlib import Path

import onnxruntime


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


def cpu_model() -> str:
    for line in Path("/proc/cpuinfo").read_text().splitlines():
        if line.startswith("model name"):
            return line.split(":", 1)[1].strip()
    return platform.processor() or "unknown"


def this_machine() -> Machine:
    return Machine(
        cpus=len(os.sched_getaffinity(0)),
        cpu_model=cpu_model(),
        load_at_start=os.getloadavg(),
        python=platform.python_version(),
        onnxruntime=onnxruntime.__version__,
    )
