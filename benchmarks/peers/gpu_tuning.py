"""Which service settings serve best on this GPU: each variant started in turn, four wrk points.

    python -m benchmarks.peers.gpu_tuning            # every variant, ~5 min
    python -m benchmarks.peers.gpu_tuning workers     # the variants whose name has "workers"

Every variant starts from ``benchmarks.peers.accelerator.CUDA_SETTINGS`` (the CUDA provider,
with the service's heuristic cuDNN algorithms and TF32 off) and changes the processes and
threads; after a warm-up, wrk measures 1 box at concurrency 1, 4 and 16 and 4
boxes at 16, 4 s each. The figures in docs/operations.md ("Serving from a GPU") come from
this command on an H200.
"""

from __future__ import annotations

import sys
import tempfile
from pathlib import Path

from benchmarks.peers.accelerator import CUDA_SETTINGS
from benchmarks.peers.measure import Requests
from benchmarks.service_bench.inputs import load_sample
from benchmarks.service_bench.loadgen import require_wrk, run_wrk
from benchmarks.service_bench.server import serve
from service.infra.settings import DEFAULT_MODEL_DIR

POINTS = ((1, 1), (1, 4), (1, 16), (4, 16))  # (boxes, concurrency)
SECONDS = 4

#: name -> CKS_* settings over CUDA_SETTINGS
VARIANTS = {
    "defaults": {},
    "8 cpu workers, 32 inferences": {"CKS_CPU_WORKERS": "8", "CKS_MAX_CONCURRENT_INFERENCES": "32"},
    "16 cpu workers, 64 inferences": {"CKS_CPU_WORKERS": "16", "CKS_MAX_CONCURRENT_INFERENCES": "64"},
    "4 workers, 8 cpu workers, 32 inferences": {
        "CKS_WORKERS": "4",
        "CKS_CPU_WORKERS": "8",
        "CKS_MAX_CONCURRENT_INFERENCES": "32",
    },
    "8 workers, 4 cpu workers, 16 inferences": {
        "CKS_WORKERS": "8",
        "CKS_CPU_WORKERS": "4",
        "CKS_MAX_CONCURRENT_INFERENCES": "16",
    },
}


def measure_variant(settings: dict[str, str], requests: Requests, log: Path) -> list[str]:
    with serve({**CUDA_SETTINGS, **settings}, log=log) as server:
        run_wrk(server.url, requests.scripts[4], 16, SECONDS)  # every batch size the points will see
        run_wrk(server.url, requests.scripts[1], 16, SECONDS / 2)
        cells = []
        for boxes, concurrency in POINTS:
            result = run_wrk(server.url, requests.scripts[boxes], concurrency, SECONDS)
            cells.append(f"{result.requests_per_s:.0f} req/s, p50 {result.p50_ms:.1f} ms")
        return cells


def main(argv: list[str]) -> int:
    require_wrk()
    wanted = {name: s for name, s in VARIANTS.items() if not argv or any(word in name for word in argv)}
    print("| settings over CUDA_SETTINGS | " + " | ".join(f"{b} box(es), c={c}" for b, c in POINTS) + " |")
    print("|---|" + "---|" * len(POINTS), flush=True)
    sample = load_sample(DEFAULT_MODEL_DIR / "samples")
    with tempfile.TemporaryDirectory(prefix="cks-gpu-tuning-") as directory:
        requests = Requests.write(Path(directory), sample)
        for index, (name, settings) in enumerate(wanted.items()):
            cells = measure_variant(settings, requests, Path(directory) / f"variant-{index}.log")
            print(f"| {name} | " + " | ".join(cells) + " |", flush=True)
    return 0


if __name__ == "__main__":
    sys.exit(main(sys.argv[1:]))
