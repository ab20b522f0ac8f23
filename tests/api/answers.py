"""The service's answers to a fixed set of requests, for the test that they never change.

``python -m tests.api.answers`` records them (``answers_before.json.gz``, recorded again, deliberately,
when a bundled calibration changes); ``test_answers_unchanged.py`` asks again and compares. The requests
cover every predict option on the bundled samples (JSON and PNG answers, the batch route), the
refusals of bad requests, and the version and scores an upload makes.
"""

from __future__ import annotations

import gzip
import hashlib
import io
import json
import time
import zipfile
from collections.abc import Iterator
from pathlib import Path
from typing import Any

from fastapi.testclient import TestClient

from service.infra.settings import Settings
from service.serving.app import create_app
from tests.samples import load_samples, model_dir, samples_by_image

RECORDED = Path(__file__).with_name("answers_before.json.gz")
TOKEN = "answers-admin-token"
ADMIN = {"Authorization": f"Bearer {TOKEN}"}
K = [[572.4114, 0.0, 325.2611], [0.0, 573.57043, 242.04899], [0.0, 0.0, 1.0]]


def _options() -> Iterator[tuple[str, dict[str, Any]]]:
    for kind in ("peak", "var", "cov"):
        for coverage in ("keypoint", "object"):
            for epsilon in (0.1, 0.3, 0.002):
                yield (
                    f"{kind}-{coverage}-{epsilon}",
                    {"nonconformity": kind, "coverage": coverage, "epsilon": epsilon},
                )
            yield f"{kind}-{coverage}-pac", {"nonconformity": kind, "coverage": coverage, "delta": 0.05}
    yield "statistics", {"include_statistics": True}
    yield "version-1", {"calibration_version": 1, "nonconformity": "var"}
    for stratify in ("difficulty", "group", ["difficulty", "group"]):
        for fallback in ("pooled", "refuse"):
            yield f"stratify-{stratify}-{fallback}", {"stratify": stratify, "group_fallback": fallback}


def _requests(samples_dir: Path) -> Iterator[tuple[str, str, dict[str, Any]]]:
    """(name, path, httpx keyword arguments) of every request whose answer is recorded."""
    doc = json.loads((samples_dir / "annotations.json").read_text())
    by_image = samples_by_image(load_samples(samples_dir, doc))
    images = sorted(by_image)
    for image_path in images:
        instances = [
            {"object": s.object, "bbox": s.bbox, "group": "left" if s.bbox[0] < 320 else None}
            for s in by_image[image_path]
        ]
        for name, options in _options():
            request = json.dumps({"instances": instances, **options})
            files = {
                "image": ("image.jpg", image_path.read_bytes(), "image/jpeg"),
                "request": (None, request),
            }
            yield f"predict/{image_path.name}/{name}", "/v1/predict", {"files": files}
    first, second = images[0], images[1]
    instances = [{"object": s.object, "bbox": s.bbox} for s in by_image[first]]
    pose = {"K": K, "samples": 20, "outer_bound": True}
    for name, options in {
        "pose": {"pose": pose},
        "pose-keypoint": {"pose": pose, "coverage": "keypoint"},
        "pose-object": {"pose": pose, "coverage": "object"},
    }.items():
        request = json.dumps({"instances": instances, **options})
        files = {"image": ("image.jpg", first.read_bytes(), "image/jpeg"), "request": (None, request)}
        yield f"predict/{first.name}/{name}", "/v1/predict", {"files": files}
    request = json.dumps({"instances": instances})
    files = {"image": ("image.jpg", first.read_bytes(), "image/jpeg"), "request": (None, request)}
    yield "png", "/v1/predict", {"files": files, "headers": {"Accept": "image/png"}}
    batch = {
        "image_0": ("a.jpg", first.read_bytes(), "image/jpeg"),
        "request_0": (None, request),
        "image_1": ("b.jpg", second.read_bytes(), "image/jpeg"),
        "request_1": (None, json.dumps({"instances": [{"object": "nothing", "bbox": [1, 1, 5, 5]}]})),
    }
    yield "batch", "/v1/predict/batch", {"files": batch}
    yield from _refusals(first, instances)


def _refusals(image: Path, instances: list[dict]) -> Iterator[tuple[str, str, dict[str, Any]]]:
    jpeg = image.read_bytes()

    def form(request: Any, data: bytes = jpeg) -> dict[str, Any]:
        raw = request if isinstance(request, str) else json.dumps(request)
        return {"files": {"image": ("image.jpg", data, "image/jpeg"), "request": (None, raw)}}

    bad = {
        "epsilon-2": {"instances": instances, "epsilon": 2},
        "unknown-object": {"instances": [{"object": "nothing", "bbox": [1, 1, 5, 5]}]},
        "box-outside": {"instances": [{"object": instances[0]["object"], "bbox": [9000, 9000, 5, 5]}]},
        "no-instances": {"instances": []},
        "unknown-field": {"instances": instances, "colour": "red"},
        "unknown-version": {"instances": instances, "calibration_version": 99},
        "pose-bad-K": {"instances": instances, "pose": {"K": [[1, 0], [0, 1]]}},
        "stratify-unknown": {"instances": instances, "stratify": "weather"},
    }
    for name, request in bad.items():
        yield f"refuse/{name}", "/v1/predict", form(request)
    yield "refuse/not-json", "/v1/predict", form("{not json")
    yield "refuse/not-image", "/v1/predict", form({"instances": instances}, b"GIF89a not an image")
    yield "refuse/truncated-jpeg", "/v1/predict", form({"instances": instances}, jpeg[: len(jpeg) // 3])
    yield "refuse/text-body", "/v1/predict", {"content": b"hello", "headers": {"Content-Type": "text/plain"}}
    yield "refuse/json-bad-base64", "/v1/predict", {"json": {"instances": instances, "image_base64": "@@@"}}


def _answer(response: Any) -> Any:
    kind = response.headers.get("content-type", "")
    if kind.startswith("image/png"):
        return {"status": response.status_code, "png_sha256": hashlib.sha256(response.content).hexdigest()}
    body = response.json()
    if isinstance(body, dict):
        body.pop("request_id", None)
        for item in body.get("items", []):
            item.get("problem", {}).pop("request_id", None)
    return {"status": response.status_code, "type": kind, "body": body}


def _upload(client: TestClient, samples_dir: Path) -> dict[str, Any]:
    """Upload the samples as a batch; the job's end and the version it made, times left out."""
    zipped = _batch_zip(samples_dir)
    response = client.post(
        "/v1/admin/calibrations", content=zipped, headers={**ADMIN, "Content-Type": "application/zip"}
    )
    assert response.status_code == 202, response.text
    job_id = response.json()["id"]
    for _ in range(1200):
        job = client.get(f"/v1/admin/jobs/{job_id}", headers=ADMIN).json()
        if job["state"] in ("succeeded", "failed", "interrupted"):
            break
        time.sleep(0.1)
    version = job.get("version")
    detail = client.get(f"/v1/admin/calibrations/{version}", headers=ADMIN).json()
    refused = client.post(
        "/v1/admin/calibrations", content=b"not a zip", headers={**ADMIN, "Content-Type": "application/zip"}
    )
    return {"job": _timeless(job), "version": _timeless(detail), "not-a-zip": _answer(refused)}


def _batch_zip(samples_dir: Path) -> bytes:
    """The samples as a zip whose bytes (and so its name and sha256) are the same every time."""
    doc = json.loads((samples_dir / "annotations.json").read_text())
    buffer = io.BytesIO()
    with zipfile.ZipFile(buffer, "w", zipfile.ZIP_DEFLATED) as archive:
        archive.writestr(zipfile.ZipInfo("annotations.json"), json.dumps(doc))
        for image in doc["images"]:
            data = (samples_dir / image["file_name"]).read_bytes()
            archive.writestr(zipfile.ZipInfo(image["file_name"]), data)
    return buffer.getvalue()


def _timeless(value: Any) -> Any:
    if isinstance(value, dict):
        return {
            k: _timeless(v)
            for k, v in value.items()
            if not any(word in k for word in ("time", "_at", "id", "seconds", "elapsed"))
        }
    if isinstance(value, list):
        return [_timeless(v) for v in value]
    return value


def collect(data_dir: Path) -> dict[str, Any]:
    """Every recorded answer of a fresh service on ``data_dir``, and the scores it stores."""
    samples_dir = model_dir() / "samples"
    settings = Settings(data_dir=data_dir, admin_token=TOKEN, inference_threads=1)
    answers: dict[str, Any] = {}
    with TestClient(create_app(settings)) as client:
        for name, path, arguments in _requests(samples_dir):
            answers[name] = _answer(client.post(path, **arguments))
        answers["upload"] = _upload(client, samples_dir)
        _, path, arguments = next(_requests(samples_dir))
        answers["predict/after-upload"] = _answer(client.post(path, **arguments))
        state = client.app.state.service
        version = answers["upload"]["version"].get("version")
        table = state.store.load_scores(state.detector.model_hash, version) if version else None
    answers["scores"] = _scores(table)
    return answers


def _scores(table: Any) -> Any:
    """Every stored score and feature of the version, by object (NaN: not labeled, as None)."""
    if table is None:
        return None

    def values(matrix: Any) -> list:
        return [None if x != x else float(x) for x in matrix.ravel()]

    return {
        block.object_name: {
            "refs": list(block.instance_refs),
            "instance_hashes": list(block.instance_hashes),
            **{f"scores/{k}": values(v) for k, v in sorted(block.scores.items())},
            **{f"features/{k}": values(v) for k, v in sorted(block.features.items())},
        }
        for block in table.objects
    }


def recorded() -> dict[str, Any]:
    return json.loads(gzip.decompress(RECORDED.read_bytes()))


if __name__ == "__main__":
    import tempfile

    with tempfile.TemporaryDirectory() as folder:
        answers = collect(Path(folder) / "data")
    RECORDED.write_bytes(gzip.compress(json.dumps(answers, sort_keys=True).encode(), mtime=0))
    print(f"{len(answers)} answers recorded in {RECORDED}")
