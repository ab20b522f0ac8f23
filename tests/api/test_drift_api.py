"""Drift without labels in process (the ASGI app): quiet on images like the calibration's, an alarm on a
blurred stream, the same figures in /metrics, and a clear answer where there is no reference.

The live stream is the bundled samples (rendered like the bundled calibration's 600 images);
the shifted stream is the same images blurred by the test with cv2 (a defocused or dirty lens).
"""

from __future__ import annotations

import json
import re
from collections import Counter
from collections.abc import Iterator
from pathlib import Path

import cv2
import numpy as np
import pytest

from tests.api.in_process import InProcess
from tests.api.test_manifest_change import copy_model
from tests.predict_client import instances_of, predict_ok
from tests.samples import Sample, samples_by_image
from tests.service_calls import ADMIN_TOKEN, assert_problem, wait_until

FEATURES = ("peak_probability", "gamma", "anisotropy")
BLUR_SIGMAS = (5.0, 7.0, 9.0)


@pytest.fixture(scope="module")
def drift_server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[InProcess]:
    """The frame-window ks test, every request computing every statistic (share 1), a history point
    every 0.2 s."""
    data = tmp_path_factory.mktemp("drift") / "data"
    fixed = {"DRIFT_FULL_STATISTICS_SHARE": 1.0, "DRIFT_HISTORY_SECONDS": 0.2}
    with InProcess(data, fixed, admin_token=ADMIN_TOKEN, drift_test="ks") as live:
        yield live


def drift(api: InProcess) -> dict:
    response = api.client.get("/v1/admin/drift", headers=api.admin)
    assert response.status_code == 200, response.text
    return response.json()


def send(api: InProcess, samples: list[Sample], transform=None) -> int:
    """One predict per sample image with all its instances; returns the instances sent."""
    sent = 0
    for image_path, group in samples_by_image(samples).items():
        image = image_path.read_bytes()
        if transform is not None:
            pixels = transform(cv2.imdecode(np.frombuffer(image, np.uint8), cv2.IMREAD_COLOR))
            image = cv2.imencode(".jpg", pixels, [cv2.IMWRITE_JPEG_QUALITY, 95])[1].tobytes()
        predict_ok(api.client, image, {"instances": instances_of(group)})
        sent += len(group)
    return sent


def blurred(sigma: float):
    return lambda pixels: cv2.GaussianBlur(pixels, (0, 0), sigma)


def test_drift_is_quiet_on_calibration_like_images_and_alarms_on_a_blurred_stream(
    drift_server: InProcess, samples: list[Sample]
) -> None:
    send(drift_server, samples)
    quiet = drift(drift_server)
    per_object = Counter(s.object for s in samples)
    assert quiet["statistic"] == "ks" and quiet["alarm_threshold"] == 0.01 and quiet["window"] == 500
    assert quiet["reference_available"] and quiet["reference_version"] == 1, quiet["reason"]
    assert len(quiet["keypoints"]) == 48 and len(quiet["objects"]) == 6
    for keypoint in quiet["keypoints"]:
        for feature in FEATURES:
            test = keypoint["features"][feature]
            assert test["live_n"] == per_object[keypoint["object"]], keypoint
            assert test["reference_n"] > 100  # the bundled calibration's instances of the object
            if test["live_n"]:
                assert 0 <= test["statistic"] <= 1 and 0 <= test["p_value"] <= 1
    alarms = [(k["keypoint"], f) for k in quiet["keypoints"] for f, t in k["features"].items() if t["alarm"]]
    assert not quiet["alarm"] and not alarms, alarms

    for sigma in BLUR_SIGMAS:
        send(drift_server, samples, blurred(sigma))
    shifted = drift(drift_server)
    assert shifted["alarm"]
    alarmed_objects = {o["object"] for o in shifted["objects"] if o["alarm"]}
    assert alarmed_objects == set(per_object), shifted["objects"]  # every object the stream shows
    alarms = [(k, f) for k in shifted["keypoints"] for f, t in k["features"].items() if t["alarm"]]
    assert len(alarms) >= 48, f"{len(alarms)} of 144 keypoint x feature tests alarm"  # 69 when written

    # the same evaluation in /metrics, and the history shows the change
    metrics = drift_server.client.get("/metrics").text
    assert re.search(r"^cks_drift_alarm_any 1\.0$", metrics, re.MULTILINE)
    keypoint, feature = alarms[0]
    labels = f'feature="{feature}",keypoint="{keypoint["keypoint"]}",object="{keypoint["object"]}"'
    assert f"cks_drift_alarm{{{labels}}} 1.0" in metrics
    assert f"cks_drift_window_size{{{labels}}} {4.0 * per_object[keypoint['object']]}" in metrics

    def latest_point() -> dict:
        return drift(drift_server)["history"][-1]

    wait_until(lambda: latest_point()["recorded"] == shifted["recorded"], "the history has the whole stream")
    assert latest_point()["alarm"] and len(latest_point()["keypoint_statistics"]) == 48

    sizes = shifted["set_sizes"]
    assert sizes["cov"]["n"] == 4 * len(samples) * 8 and sizes["peak"]["n"] == 0
    quantiles = sizes["cov"]["semi_major_px"]["quantiles"]
    assert 0 < quantiles["p05"] <= quantiles["p50"] <= quantiles["p95"]


def test_drift_needs_the_admin_token(drift_server: InProcess) -> None:
    assert_problem(drift_server.client.get("/v1/admin/drift"), 401, "Bearer")


def test_a_version_without_features_is_said_not_a_server_error(
    model_path: Path, samples: list[Sample], tmp_path: Path
) -> None:
    """A calibration made before features were stored (its bundle stripped of them here)."""
    model = copy_model(model_path, tmp_path / "model")
    bundle = dict(np.load(model / "default_calibration.npz", allow_pickle=False))
    stripped = {key: value for key, value in bundle.items() if "/features/" not in key}
    assert len(stripped) < len(bundle), "the bundled calibration carries features"
    np.savez(model / "default_calibration.npz", **stripped)
    with InProcess(tmp_path / "data", admin_token=ADMIN_TOKEN, model_dir=model) as api:
        send(api, samples[:3])
        report = drift(api)
        assert not report["reference_available"] and not report["alarm"]
        assert "carries no heatmap features" in report["reason"] and report["reference_version"] == 1
        assert all(t["statistic"] is None for k in report["keypoints"] for t in k["features"].values())
        assert "cks_drift_reference_version 0.0" in api.client.get("/metrics").text


def test_drift_off_answers_404(tmp_path: Path) -> None:
    """(That such a server exports no cks_drift_* metrics is checked on a server process of its own,
    tests/deploy/test_console.py: here other apps of this test process may have drift monitors.)"""
    with InProcess(tmp_path / "data", admin_token=ADMIN_TOKEN, drift_enabled=False) as api:
        assert_problem(api.client.get("/v1/admin/drift", headers=api.admin), 404, "CKS_DRIFT_ENABLED")


def test_the_drift_document_is_json_with_the_console_keys(drift_server: InProcess) -> None:
    body = drift(drift_server)
    assert set(body) >= {
        "window",
        "statistic",
        "alarm_threshold",
        "keypoints",
        "objects",
        "history",
        "set_sizes",
    }
    json.dumps(body, allow_nan=False)  # no NaN or infinity for a browser's JSON.parse


def test_the_samples_sent_again_and_again_are_twelve_looks_and_no_alarm(
    samples: list[Sample], tmp_path: Path
) -> None:
    """Issue #28: a server that received the 12 bundled samples 18 times each showed 105 of 144
    tests in alarm under ks; the sequential default counts each image once."""
    with InProcess(tmp_path / "data", admin_token=ADMIN_TOKEN) as api:
        for _ in range(18):
            send(api, samples)
        report = drift(api)
    images = len(samples_by_image(samples))
    assert report["statistic"] == "sequential" and report["frames"] == 18 * images
    assert report["independent_looks"] == images and not report["alarm"], report["evidence"]
    assert not any(t["alarm"] for k in report["keypoints"] for t in k["features"].values())
