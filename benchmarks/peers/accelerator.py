"""Where the model runs in the peer benchmark: the CPU, or a GPU (``bench_peers --gpu``).

Every server reads the same ``CKS_EXECUTION_PROVIDERS`` from its environment: the service as its
setting, the peers through ``Pipeline``; on a GPU the service runs with the ``cuda`` image's
settings (Dockerfile), as a user of that image would.
"""

from __future__ import annotations

import os
import shutil
import subprocess

from service.infra.settings import Settings

CUDA = "CUDAExecutionProvider"
#: the model on the GPU; the service gives CUDA full fp32 and heuristic cuDNN algorithms
#: (``service.detector.session.PROVIDER_DEFAULTS``), the peers' sessions too
CUDA_SETTINGS = {"CKS_EXECUTION_PROVIDERS": f"{CUDA},CPUExecutionProvider"}
#: what served best on the GPU machine measured (docs/operations.md "Serving from a GPU"): the
#: CPU work (decode, crop, sets) spread over processes, each request its own run
GPU_SETTINGS = {
    **CUDA_SETTINGS,
    "CKS_WORKERS": str(max(1, len(os.sched_getaffinity(0)) // 2)),
    "CKS_MAX_CONCURRENT_INFERENCES": "16",
}


def execution_providers() -> tuple[tuple[str, ...], dict[str, dict[str, str]]]:
    """The providers of this run and their options, as the service reads them
    (``CKS_EXECUTION_PROVIDERS``, ``CKS_EXECUTION_PROVIDER_OPTIONS``)."""
    settings = Settings()
    return settings.model.execution_providers, settings.model.execution_provider_options


def on_gpu() -> bool:
    return CUDA in execution_providers()[0]


def gpu_names() -> str:
    """The GPUs and driver ``nvidia-smi`` reports, or why there is none to report."""
    if shutil.which("nvidia-smi") is None:
        return "no nvidia-smi"
    query = ["nvidia-smi", "--query-gpu=name,memory.total,driver_version", "--format=csv,noheader"]
    found = subprocess.run(query, capture_output=True, text=True, timeout=30)
    rows = [row.strip() for row in found.stdout.splitlines() if row.strip()]
    return "; ".join(f"GPU {row} (name, memory, driver)" for row in rows) or found.stderr.strip()
