"""Operations endpoints: liveness, readiness (and its 503), Prometheus metrics."""

from __future__ import annotations

import json
import re
from collections.abc import Iterator
from pathlib import Path

import pytest

from tests.api.in_process import InProcess
from tests.predict_client import instances_of, predict_ok
from tests.samples import Sample, batch_zip, samples_by_image
from tests.service_calls import ADMIN_TOKEN, assert_problem


def metric_samples(text: str, name: str) -> dict[str, float]:
    """Sample lines of one metric family: '{labels}' (or '') -> value."""
    found = {}
    for line in text.splitlines():
        match = re.match(rf"^{re.escape(name)}(\{{.*\}})?\s+(\S+)$", line)
        if match:
            found[match.group(1) or ""] = float(match.group(2))
    return found


def test_healthz(api: InProcess) -> None:
    response = api.client.get("/healthz")
    assert response.status_code == 200
    assert response.json() == {"status": "ok"}


def test_readyz_with_an_active_calibration(api: InProcess) -> None:
    response = api.client.get("/readyz")
    assert response.status_code == 200, response.text
    body = response.json()
    model = api.client.get("/v1/model").json()
    age = body.pop("cache_age_seconds")
    assert 0 <= age < 5, age  # polled every CKS_STORE_POLL_SECONDS (1 s)
    assert body == {
        "status": "ready",
        "model": model["name"],
        "model_hash": model["hash"],
        "active_calibration": 1,
        "store": "ok",
        "store_error": None,
    }


@pytest.fixture(scope="module")
def unbootstrapped(tmp_path_factory: pytest.TempPathFactory) -> Iterator[InProcess]:
    data = tmp_path_factory.mktemp("fresh") / "data"
    with InProcess(data, admin_token=ADMIN_TOKEN, bootstrap_calibration="false") as live:
        yield live


def test_readyz_is_503_without_an_active_calibration(
    unbootstrapped: InProcess, samples: list[Sample]
) -> None:
    assert unbootstrapped.client.get("/healthz").status_code == 200  # alive, not ready
    assert_problem(unbootstrapped.client.get("/readyz"), 503, "no calibration is active")
    assert unbootstrapped.versions() == []
    path, group = next(iter(samples_by_image(samples).items()))
    response = unbootstrapped.client.post(
        "/v1/predict",
        files={"image": ("i.jpg", path.read_bytes(), "image/jpeg")},
        data={"request": json.dumps({"instances": instances_of(group)})},
    )
    assert_problem(response, 503, "no calibration is active")


def test_readyz_becomes_200_after_a_first_calibration(
    unbootstrapped: InProcess, samples_dir: Path, coco: dict
) -> None:
    job = unbootstrapped.calibrate(
        batch_zip(samples_dir, coco, images=3), activate=True, force=True, reason="first calibration"
    )
    response = unbootstrapped.client.get("/readyz")
    assert response.status_code == 200, response.text
    assert response.json()["active_calibration"] == job["result"]["version"] == 1


def test_metrics(api: InProcess, samples: list[Sample], samples_dir: Path, coco: dict) -> None:
    path, group = next(iter(samples_by_image(samples).items()))
    predict_ok(api.client, path.read_bytes(), {"instances": instances_of(group)})
    api.calibrate(batch_zip(samples_dir, coco, images=2))
    api.client.get("/v1/admin/calibrations/123456", headers=api.admin)  # a 404 on a templated route

    response = api.client.get("/metrics")
    assert response.status_code == 200
    assert response.headers["content-type"].startswith("text/plain")
    text = response.text

    requests = metric_samples(text, "cks_http_requests_total")
    predict_label = '{method="POST",route="/v1/predict",status="200"}'
    assert requests.get(predict_label, 0) >= 1, requests
    detail_label = '{method="GET",route="/v1/admin/calibrations/{version}",status="404"}'
    assert requests.get(detail_label, 0) >= 1, requests
    assert not any("123456" in labels for labels in requests), "raw paths must not become label values"
    latency = metric_samples(text, "cks_http_request_seconds_count")
    assert latency.get('{method="POST",route="/v1/predict"}', 0) >= 1, latency

    batch_count = metric_samples(text, "cks_inference_batch_size_count")
    batch_sum = metric_samples(text, "cks_inference_batch_size_sum")
    assert sum(batch_count.values()) >= 1 and sum(batch_sum.values()) >= len(group), (batch_count, batch_sum)
    assert any(metric_samples(text, "cks_inference_batch_size_bucket").values())

    jobs = metric_samples(text, "cks_calibration_jobs_total")
    assert jobs.get('{state="succeeded"}', 0) >= 1, jobs
