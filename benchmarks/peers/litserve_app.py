"""LitServe, as its docs recommend for a CPU model: two inference workers on the CPU (one per core,
``workers_per_device=2``), one intra-op thread each, dynamic batching of up to 8 requests with a
2 ms batch timeout; one API server per inference worker (LitServe's default). With ``bench_peers
--gpu`` its workers share the GPU (``accelerator='cuda'``), as many as the service's worker processes
(``CKS_WORKERS``), batching as before.

    python -m benchmarks.peers.litserve_app PORT

(No ``from __future__ import annotations`` here: LitServe reads ``decode_request``'s annotation
as a class to know that it wants the form.)
"""

import os
import sys

import litserve as ls
from fastapi import Request

from benchmarks.peers.accelerator import on_gpu
from benchmarks.peers.pipeline import Pipeline, Prepared

MAX_BATCH, BATCH_TIMEOUT_S = 8, 0.002


def workers() -> int:
    """Two on the CPU (one per core); on a GPU as many as the service's worker processes."""
    return int(os.environ.get("CKS_WORKERS", "2")) if on_gpu() else 2


class KeypointAPI(ls.LitAPI):
    def setup(self, device: str) -> None:
        self.pipeline = Pipeline(intra_op_threads=1)

    def decode_request(self, request: Request) -> Prepared:
        return self.pipeline.prepare(request["image"].file.read(), request["request"])

    def batch(self, inputs: list[Prepared]) -> list[Prepared]:
        return inputs

    def predict(self, batch: list[Prepared]) -> list[dict]:
        heatmaps = self.pipeline.infer_many(batch)
        return [self.pipeline.answer(p, h) for p, h in zip(batch, heatmaps, strict=True)]

    def unbatch(self, output: list[dict]) -> list[dict]:
        return output

    def encode_response(self, output: dict) -> dict:
        return output


def main(port: int) -> None:
    api = KeypointAPI(max_batch_size=MAX_BATCH, batch_timeout=BATCH_TIMEOUT_S, api_path="/v1/predict")
    accelerator = "cuda" if on_gpu() else "cpu"
    server = ls.LitServer(
        api, accelerator=accelerator, workers_per_device=workers(), healthcheck_path="/readyz"
    )
    server.run(port=port, log_level="warning", generate_client_file=False)


if __name__ == "__main__":
    main(int(sys.argv[1]))
