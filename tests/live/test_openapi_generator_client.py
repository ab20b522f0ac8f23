"""A client generated from openapi/openapi.json by a third generator family, openapi-generator's
``python`` generator (Java; the jar comes with the pinned PyPI wheel ``openapi-generator-cli``),
as a user would make one: generated untouched, imported, then driven against a live server through
predict (JSON and form, the drawing), batches (JSON and form), uploads (raw and form), jobs,
activation, an audit and typed errors, every error status back as the document's ``Problem``."""

from __future__ import annotations

import base64
import subprocess
import time
from collections.abc import Iterator
from pathlib import Path
from types import ModuleType
from typing import Any

import pydantic
import pytest

from service.infra.settings import PACKAGE_ROOT
from tests.api.in_process import OnLoopback
from tests.live.generated_clients import MAX_REQUEST_BYTES, generated_client_server, imported_package
from tests.predict_client import instances_of
from tests.samples import Sample, batch_zip, samples_by_image
from tests.service_calls import ADMIN_TOKEN

PACKAGE = "cks_openapi_generator_client"
# What the generator says about itself, not about the document: its OpenAPI 3.1 support is "beta",
# and the other two it also says for a minimal valid 3.0.3 document with one schema and a
# multipart array of files (openapi-generator-cli 7.26.0). Any other warning fails the test.
KNOWN_WARNINGS = (
    "OpenAPI 3.1 support is still in beta",
    "Failed to get the schema name: null",
    "Could not compute datatypeWithEnum from bytes, null",
)


@pytest.fixture(scope="module")
def client(tmp_path_factory: pytest.TempPathFactory) -> Iterator[ModuleType]:
    """The generated package, imported from a fresh generation."""
    out = tmp_path_factory.mktemp("openapi-generator") / "client"
    document = PACKAGE_ROOT / "openapi" / "openapi.json"
    command = ["openapi-generator-cli", "generate", "-g", "python", "-i", str(document), "-o", str(out)]
    run = subprocess.run(
        [*command, "--additional-properties", f"packageName={PACKAGE}"],
        capture_output=True,
        text=True,
        timeout=300,
    )
    output = run.stdout + run.stderr
    assert run.returncode == 0, output
    warnings = [
        line for line in output.splitlines() if "WARN" in line and not any(w in line for w in KNOWN_WARNINGS)
    ]
    assert not warnings, "\n".join(warnings)
    with imported_package(out, PACKAGE, [""]) as (package,):
        yield package


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[OnLoopback]:
    """No calibration yet (predict answers 503 until one is activated), small request limit."""
    data = tmp_path_factory.mktemp("openapi-generator-client") / "data"
    with generated_client_server(data) as live:
        yield live


def problem_of(call: Any, status: int, c: ModuleType) -> Any:
    """The parsed Problem of the error the call raises, with the request's id in body and header."""
    with pytest.raises(c.ApiException) as raised:
        call()
    error = raised.value
    assert error.status == status, error.body
    problem = error.data
    assert isinstance(problem, c.Problem), error.body
    assert problem.status == status and problem.detail
    assert problem.request_id == error.headers["x-request-id"]
    return problem


def wait(admin: Any, job: Any) -> Any:
    for _ in range(600):
        job = admin.get_job(job.id)
        if job.state in ("succeeded", "failed", "interrupted"):
            return job
        time.sleep(0.2)
    raise AssertionError(f"job {job.id} still {job.state}")


def test_an_openapi_generator_client_drives_every_kind_of_call(
    client: ModuleType, server: OnLoopback, samples: list[Sample], samples_dir: Path, coco: dict
) -> None:
    c = client
    anyone_client = c.ApiClient(c.Configuration(host=server.url))
    admin = c.AdminApi(c.ApiClient(c.Configuration(host=server.url, access_token=ADMIN_TOKEN)))
    prediction = c.PredictionApi(anyone_client)
    images = [(path.read_bytes(), instances_of(group)) for path, group in samples_by_image(samples).items()]
    image, instances = images[0]

    def parameters(instances: list[dict], **options: Any) -> Any:
        return c.PredictParameters.from_dict({"instances": instances, **options})

    def as_json(image: bytes, instances: list[dict], **options: Any) -> Any:
        body = {"image_base64": base64.b64encode(image).decode(), "instances": instances, **options}
        return c.PredictJson.from_dict(body)

    jpeg = ("image.jpg", image)
    model = c.ModelApi(anyone_client).model_info()
    assert isinstance(model, c.ModelInfo) and model.manifest.keypoints

    unready = problem_of(lambda: prediction.predict_form(image=jpeg, request=parameters(instances)), 503, c)
    assert "calibration" in unready.detail.lower()
    stranger = c.AdminApi(c.ApiClient(c.Configuration(host=server.url, access_token="not-the-token-at-all")))
    problem_of(stranger.list_calibrations, 401, c)

    whole = batch_zip(samples_dir, coco)
    first = wait(admin, admin.upload_calibration(body=whole, name="first"))
    assert first.state == "succeeded" and first.version == 1, first
    refused = problem_of(lambda: admin.activate_calibration(1, activation_in=c.ActivationIn()), 409, c)
    assert "CKS_MIN_CALIBRATION_INSTANCES" in refused.detail
    forced = c.ActivationIn(force=True, reason="generated client test: the samples are below the floor")
    assert admin.activate_calibration(1, activation_in=forced).version == 1

    answer = prediction.predict_form(image=jpeg, request=parameters(instances))
    assert isinstance(answer, c.PredictResponse) and len(answer.instances) == len(instances)
    assert {keypoint.set.actual_instance.type for keypoint in answer.instances[0].keypoints} <= {
        "ball",
        "ellipse",
        "unbounded",
    }
    assert prediction.predict(as_json(image, instances)).to_dict() == answer.to_dict()
    batch = c.BatchJson.from_dict({"items": [as_json(i, s).to_dict() for i, s in images[:3]]})
    items = prediction.predict_batch(batch).items
    assert [item.status for item in items] == [200, 200, 200]
    assert items[0].result.to_dict() == answer.to_dict()
    parts = prediction.predict_batch_form(image_0=jpeg, request_0=parameters(instances))
    assert parts.items[0].result.to_dict() == answer.to_dict()
    drawing = prediction.predict_png_form(image=jpeg, request=parameters(instances))
    assert drawing.startswith(b"\x89PNG\r\n\x1a\n")
    assert prediction.predict_png(as_json(image, instances)).startswith(b"\x89PNG\r\n\x1a\n")

    part = batch_zip(samples_dir, coco, images=6)
    second = wait(admin, admin.upload_calibration_form(file=("batch.zip", part), name="part"))
    assert second.state == "succeeded" and second.version == 2, second
    comparison = admin.compare_calibration(2)
    assert isinstance(comparison, c.ComparisonOut) and not comparison.allowed
    assert admin.activate_calibration(2, activation_in=forced).version == 2
    rollback = c.ActivationIn(force=True, reason="roll back to the whole batch")
    assert admin.activate_calibration(1, activation_in=rollback).version == 1
    assert admin.get_calibration(1).active
    actions = [entry.action for entry in admin.audit_trail().entries]
    assert actions.count("activation") >= 3 and "upload" in actions, actions

    audit_job = wait(admin, admin.start_audit_form(file=("batch.zip", whole), version=2, dedupe=True))
    assert audit_job.state == "succeeded", audit_job
    audit = admin.get_audit(audit_job.result["audit"])
    assert isinstance(audit, c.AuditOut) and audit.version == 2

    again = c.UploadCalibrationOverridesParameter(
        allow_duplicate=True, reason="the same batch again, on purpose"
    )
    third = wait(admin, admin.upload_calibration(body=whole, overrides=again))
    assert third.state == "succeeded" and third.version == 3, third
    no_reason = c.UploadCalibrationOverridesParameter(force=True)
    refused = problem_of(lambda: admin.upload_calibration(body=whole, overrides=no_reason), 422, c)
    assert "force needs a reason" in refused.detail

    problem_of(lambda: admin.get_calibration(999), 404, c)
    huge = ("big.jpg", b"\xff" * MAX_REQUEST_BYTES)
    problem_of(lambda: prediction.predict_form(image=huge, request=parameters(instances)), 413, c)
    gif = ("a.gif", b"GIF89a not a picture")
    problem_of(lambda: prediction.predict_png_form(image=gif, request=parameters(instances)), 415, c)
    with pytest.raises(pydantic.ValidationError, match="epsilon"):  # the client checks the schema first
        as_json(image, instances, epsilon=2)
    unchecked = as_json(image, instances).model_copy(update={"epsilon": 2})  # copies are not checked
    assert problem_of(lambda: prediction.predict(unchecked), 422, c).errors  # and so does the server
