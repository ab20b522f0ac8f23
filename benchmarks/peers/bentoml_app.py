"""BentoML 1.4, as its docs recommend for a CPU model: ``workers=2`` (one process per core),
one intra-op thread each, the image as a file part and the request as a form field; no adaptive
batching (``batchable`` needs one array per request and the crops per image vary).

    python -m benchmarks.peers.bentoml_app PORT
"""

from __future__ import annotations

import subprocess
import sys
from pathlib import Path

import bentoml

from benchmarks.peers.pipeline import Pipeline

WORKERS = 2


@bentoml.service(workers=WORKERS, resources={"cpu": str(WORKERS)}, logging={"access": {"enabled": False}})
class Keypoints:
    def __init__(self) -> None:
        self.pipeline = Pipeline(intra_op_threads=1)

    @bentoml.api(route="/v1/predict")
    def predict(self, image: Path, request: dict) -> dict:  # BentoML parses the JSON part
        return self.pipeline(image.read_bytes(), request)


if __name__ == "__main__":
    command = [
        "bentoml",
        "serve",
        "benchmarks.peers.bentoml_app:Keypoints",
        "--port",
        sys.argv[1],
        "--host",
        "127.0.0.1",
    ]
    sys.exit(subprocess.call(command))
