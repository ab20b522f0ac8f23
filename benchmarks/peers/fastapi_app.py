"""Plain FastAPI: what a user writes in a dozen lines. One uvicorn worker; onnxruntime's default
intra-op threads (every core for one request), FastAPI's threadpool for the sync endpoint.

    python -m benchmarks.peers.fastapi_app PORT
"""

from __future__ import annotations

import sys

import uvicorn
from fastapi import FastAPI, File, Form

from benchmarks.peers.pipeline import Pipeline

pipeline = Pipeline(intra_op_threads=0)
app = FastAPI()


@app.get("/readyz")
def ready() -> dict:
    return {"ready": True}


@app.post("/v1/predict")
def predict(image: bytes = File(), request: str = Form()) -> dict:
    return pipeline(image, request)


if __name__ == "__main__":
    uvicorn.run(app, host="127.0.0.1", port=int(sys.argv[1]), log_level="warning", access_log=False)
