"""Ray Serve, as its docs recommend for a CPU model: two replicas (``num_cpus=1`` each, one per
core), one intra-op thread each, a FastAPI ingress and ``@serve.batch`` (up to 8 requests, 2 ms
wait) around inference; decoding and cropping run per request in the replica.

    python -m benchmarks.peers.ray_app PORT
"""

from __future__ import annotations

import signal
import sys
import threading

import ray
from fastapi import FastAPI, File, Form
from ray import serve

from benchmarks.peers.pipeline import Pipeline, Prepared

REPLICAS, MAX_BATCH, BATCH_WAIT_S = 2, 8, 0.002
app = FastAPI()


@serve.deployment(num_replicas=REPLICAS, ray_actor_options={"num_cpus": 1}, max_ongoing_requests=32)
@serve.ingress(app)
class Keypoints:
    def __init__(self) -> None:
        self.pipeline = Pipeline(intra_op_threads=1)

    @serve.batch(max_batch_size=MAX_BATCH, batch_wait_timeout_s=BATCH_WAIT_S)
    async def infer(self, prepared: list[Prepared]) -> list[dict]:
        heatmaps = self.pipeline.infer_many(prepared)
        return [self.pipeline.answer(p, h) for p, h in zip(prepared, heatmaps, strict=True)]

    @app.get("/readyz")
    def ready(self) -> dict:
        return {"ready": True}

    @app.post("/v1/predict")
    async def predict(self, image: bytes = File(), request: str = Form()) -> dict:
        return await self.infer(self.pipeline.prepare(image, request))


def main(port: int) -> None:
    ray.init(num_cpus=REPLICAS, include_dashboard=False, log_to_driver=False)
    serve.start(http_options={"host": "127.0.0.1", "port": port})
    serve.run(Keypoints.bind(), route_prefix="/")
    stop = threading.Event()
    signal.signal(signal.SIGINT, lambda *_: stop.set())
    signal.signal(signal.SIGTERM, lambda *_: stop.set())
    stop.wait()
    serve.shutdown()
    ray.shutdown()


if __name__ == "__main__":
    main(int(sys.argv[1]))
