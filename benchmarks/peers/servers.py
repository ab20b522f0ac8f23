"""The servers compared: the service (its default model, its int8 variant) and each peer, started alike."""

from __future__ import annotations

import os
import sys
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

from benchmarks.harness import Server, free_port, launch, serve
from service.detector.session import usable_cores
from service.infra.settings import DEFAULT_MODEL_DIR

INT8_MODEL_DIR = DEFAULT_MODEL_DIR.parent / "lmo-synth-unet-int8"


@dataclass(frozen=True)
class Contender:
    """One server: how to start it and the settings it runs with (and why)."""

    name: str
    module: str | None  # benchmarks.peers.<module> PORT; None = the service itself
    settings: str
    startup_timeout_s: float = 120
    settings_on_gpu: str | None = None  # where ``bench_peers --gpu`` changes them
    model_dir: Path | None = None  # the service's CKS_MODEL_DIR (None: its default model)
    workers: int = 1  # the service's CKS_WORKERS

    @property
    def is_peer(self) -> bool:
        return self.module is not None

    @property
    def variant(self) -> str | None:
        """The ``model.variant`` the service's answers must name (None for a peer)."""
        if self.is_peer:
            return None
        return "original" if self.model_dir is None else "int8"

    def described(self, gpu: bool) -> str:
        return self.settings_on_gpu if gpu and self.settings_on_gpu else self.settings

    @contextmanager
    def running(self, log: Path) -> Iterator[Server]:
        if self.module is None:
            settings = {"CKS_MODEL_DIR": str(self.model_dir)} if self.model_dir else {}
            settings |= {"CKS_WORKERS": str(self.workers)} if self.workers > 1 else {}
            with serve(settings, log=log) as server:
                yield server
            return
        port = free_port()
        argv = [sys.executable, "-m", f"benchmarks.peers.{self.module}", str(port)]
        with launch(argv, dict(os.environ), port, log, self.startup_timeout_s) as server:
            yield server


SERVICE = Contender(
    "service",
    None,
    "its defaults (`keypoint-service serve`, no `CKS_*` set): one worker; a request alone in the "
    "process runs on every core, and beside others each request's crops are one run of one intra-op "
    "thread on the request's own thread, concurrent runs in parallel; intra-op threads sleep between "
    "the pieces of a run instead of spinning",
)
SERVICE_INT8 = Contender(
    "service int8",
    None,
    "`CKS_MODEL_DIR=models/lmo-synth-unet-int8` (the bundled int8 variant, onnxruntime static "
    "quantization, with its own calibration; a CPU variant, so not in `--gpu` runs) and one worker per "
    f"core (`CKS_WORKERS={usable_cores()}`, as LitServe, BentoML and Ray Serve run one process per core): "
    "a different model, so its answers are checked against its own first answer, not the float32 sets",
    model_dir=INT8_MODEL_DIR,
    workers=usable_cores(),
)
SERVICE_ON_GPU = Contender(
    "service",
    None,
    "`benchmarks/peers/accelerator.py` `GPU_SETTINGS`: the CUDA provider with heuristic cuDNN algorithms "
    "and TF32 off, one worker process per two cores (`CKS_WORKERS`), each request's crops one run, "
    "`CKS_MAX_CONCURRENT_INFERENCES=16` per worker",
)
PEERS = (
    Contender(
        "FastAPI",
        "fastapi_app",
        "one uvicorn worker, a sync endpoint (FastAPI's threadpool), onnxruntime's default intra-op "
        "threads (every core for one request): the dozen lines a user writes first",
        settings_on_gpu="one uvicorn worker, a sync endpoint (FastAPI's threadpool), the session on "
        "`CKS_EXECUTION_PROVIDERS` (the GPU): the dozen lines a user writes first",
    ),
    Contender(
        "LitServe",
        "litserve_app",
        "`workers_per_device=2` on `accelerator='cpu'` (one inference process per core, as LitServe's "
        "docs advise for CPU models), one intra-op thread each, `max_batch_size=8`, `batch_timeout=0.002` "
        "(dynamic batching), one API server per worker (LitServe's default)",
        settings_on_gpu="`accelerator='cuda'` with as many workers as the service's `CKS_WORKERS` sharing "
        "the GPU (`workers_per_device`), `max_batch_size=8`, `batch_timeout=0.002` (dynamic batching), "
        "one API server per worker (LitServe's default)",
    ),
    Contender(
        "BentoML",
        "bentoml_app",
        "`@bentoml.service(workers=2)` (one process per core, as BentoML's docs advise for CPU-bound "
        "models), one intra-op thread each, the image as a file part; no adaptive batching (it needs one "
        "array per request, and the crops per image vary)",
    ),
    Contender(
        "Ray Serve",
        "ray_app",
        "two replicas with `num_cpus=1` (one per core), one intra-op thread each, a FastAPI ingress, "
        "`@serve.batch(max_batch_size=8, batch_wait_timeout_s=0.002)` around inference (Ray Serve's "
        "dynamic batching); a local Ray started by the app",
        startup_timeout_s=300,
    ),
)
