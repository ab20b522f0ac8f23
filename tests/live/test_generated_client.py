"""A client generated from openapi/openapi.json with openapi-python-client, as a user in any
language would make one: generated with no warning and no hand fix, then driven against a live
server through every kind of call, and every error status back as a parsed ``Problem``."""

from __future__ import annotations

import base64
import subprocess
import time
from collections.abc import Iterator
from io import BytesIO
from pathlib import Path
from types import SimpleNamespace
from typing import Any

import pytest

from service.infra.settings import PACKAGE_ROOT
from tests.api.in_process import OnLoopback
from tests.live.generated_clients import MAX_REQUEST_BYTES, generated_client_server, imported_package
from tests.predict_client import instances_of
from tests.samples import Sample, batch_zip, samples_by_image
from tests.service_calls import ADMIN_TOKEN

PACKAGE = "conformal_keypoint_service_client"


@pytest.fixture(scope="module")
def generated(tmp_path_factory: pytest.TempPathFactory) -> Iterator[SimpleNamespace]:
    """The generated package's modules, imported from a fresh generation."""
    out = tmp_path_factory.mktemp("generated") / "client"
    command = ["openapi-python-client", "generate", "--path", str(PACKAGE_ROOT / "openapi" / "openapi.json")]
    run = subprocess.run([*command, "--output-path", str(out)], capture_output=True, text=True, timeout=300)
    output = run.stdout + run.stderr
    assert run.returncode == 0, output
    assert "warning" not in output.lower(), output
    names = ["client", "types", "models"] + [
        f"api.{tag}.{operation}"
        for tag, operation in [
            ("model", "model_info"),
            ("prediction", "predict"),
            ("prediction", "predict_form"),
            ("prediction", "predict_png"),
            ("prediction", "predict_png_form"),
            ("prediction", "predict_batch"),
            ("prediction", "predict_batch_form"),
            ("admin", "upload_calibration"),
            ("admin", "upload_calibration_form"),
            ("admin", "get_job"),
            ("admin", "get_calibration"),
            ("admin", "compare_calibration"),
            ("admin", "activate_calibration"),
            ("admin", "audit_trail"),
            ("admin", "list_calibrations"),
            ("admin", "start_audit"),
            ("admin", "start_audit_form"),
            ("admin", "get_audit"),
        ]
    ]
    with imported_package(out, PACKAGE, names) as modules:
        yield SimpleNamespace(
            **{name.split(".")[-1]: module for name, module in zip(names, modules, strict=True)}
        )


@pytest.fixture(scope="module")
def server(tmp_path_factory: pytest.TempPathFactory) -> Iterator[OnLoopback]:
    """No calibration yet (predict answers 503 until one is activated), small request limit."""
    data = tmp_path_factory.mktemp("generated-client") / "data"
    with generated_client_server(data) as live:
        yield live


def problem_of(response: Any, status: int, g: SimpleNamespace) -> Any:
    """The parsed Problem of an error answer, with the request's id in the body and the header."""
    assert response.status_code == status, response.content[:500]
    problem = response.parsed
    assert isinstance(problem, g.models.Problem), problem
    assert problem.status == status and problem.detail
    assert problem.request_id == response.headers["x-request-id"]
    return problem


def wait(g: SimpleNamespace, admin: Any, job: Any) -> Any:
    assert not isinstance(job, g.models.Problem), job
    for _ in range(600):
        job = g.get_job.sync(job.id, client=admin)
        if job.state in ("succeeded", "failed", "interrupted"):
            return job
        time.sleep(0.2)
    raise AssertionError(f"job {job.id} still {job.state}")


def zip_file(data: bytes) -> Any:
    return {"payload": BytesIO(data), "file_name": "batch.zip", "mime_type": "application/zip"}


def test_a_generated_client_drives_every_kind_of_call(
    generated: SimpleNamespace, server: OnLoopback, samples: list[Sample], samples_dir: Path, coco: dict
) -> None:
    g, m = generated, generated.models
    File = g.types.File
    anyone = g.client.Client(base_url=server.url, timeout=120)
    admin = g.client.AuthenticatedClient(base_url=server.url, token=ADMIN_TOKEN, timeout=120)
    images = [(path.read_bytes(), instances_of(group)) for path, group in samples_by_image(samples).items()]
    image, instances = images[0]

    def parameters(instances: list[dict], **options: Any) -> Any:
        return m.PredictParameters.from_dict({"instances": instances, **options})

    def as_json(image: bytes, instances: list[dict], **options: Any) -> Any:
        body = {"image_base64": base64.b64encode(image).decode(), "instances": instances, **options}
        return m.PredictJson.from_dict(body)

    def form(image: bytes, instances: list[dict], body: type = m.PredictFormBody) -> Any:
        picture = File(payload=BytesIO(image), file_name="image.jpg", mime_type="image/jpeg")
        return body(image=picture, request=parameters(instances))  # each operation has its form class

    model = g.model_info.sync(client=anyone)
    assert isinstance(model, m.ModelInfo) and model.manifest.keypoints

    problem_of(
        g.predict_form.sync_detailed(client=anyone, body=form(image, instances)), 503, g
    )  # none active
    stranger = g.client.AuthenticatedClient(base_url=server.url, token="not-the-token-at-all")
    problem_of(g.list_calibrations.sync_detailed(client=stranger), 401, g)

    whole = batch_zip(samples_dir, coco)
    first = wait(
        g, admin, g.upload_calibration.sync(client=admin, body=File(**zip_file(whole)), name="first")
    )
    assert first.state == "succeeded" and first.version == 1, first
    refused = problem_of(g.activate_calibration.sync_detailed(1, client=admin, body=m.ActivationIn()), 409, g)
    assert "CKS_MIN_CALIBRATION_INSTANCES" in refused.detail
    forced = m.ActivationIn(force=True, reason="generated client test: the samples are below the floor")
    assert g.activate_calibration.sync(1, client=admin, body=forced).version == 1

    answer = g.predict_form.sync(client=anyone, body=form(image, instances))
    assert isinstance(answer, m.PredictResponse) and len(answer.instances) == len(instances)
    same = g.predict.sync(client=anyone, body=as_json(image, instances))
    assert same.to_dict() == answer.to_dict()
    batch = m.BatchJson.from_dict({"items": [as_json(i, s).to_dict() for i, s in images[:3]]})
    items = g.predict_batch.sync(client=anyone, body=batch).items
    assert [item.status for item in items] == [200, 200, 200]
    assert items[0].result.to_dict() == answer.to_dict()
    parts = m.PredictBatchFormBody(image_0=form(image, instances).image, request_0=parameters(instances))
    assert g.predict_batch_form.sync(client=anyone, body=parts).items[0].result.to_dict() == answer.to_dict()
    drawing = g.predict_png_form.sync(client=anyone, body=form(image, instances, m.PredictPngFormBody))
    assert drawing.payload.read().startswith(b"\x89PNG\r\n\x1a\n")
    drawn = g.predict_png.sync(client=anyone, body=as_json(image, instances))
    assert drawn.payload.read().startswith(b"\x89PNG\r\n\x1a\n")

    part = batch_zip(samples_dir, coco, images=6)
    upload = m.UploadCalibrationFormBody(file=File(**zip_file(part)))
    second = wait(g, admin, g.upload_calibration_form.sync(client=admin, body=upload, name="part"))
    assert second.state == "succeeded" and second.version == 2, second
    comparison = g.compare_calibration.sync(2, client=admin)
    assert isinstance(comparison, m.ComparisonOut) and not comparison.allowed
    assert g.activate_calibration.sync(2, client=admin, body=forced).version == 2
    rollback = m.ActivationIn(force=True, reason="roll back to the whole batch")
    assert g.activate_calibration.sync(1, client=admin, body=rollback).version == 1
    assert g.get_calibration.sync(1, client=admin).active
    actions = [entry.action for entry in g.audit_trail.sync(client=admin).entries]
    assert actions.count("activation") >= 3 and "upload" in actions, actions

    audit_body = m.StartAuditFormBody(file=File(**zip_file(whole)))  # less what version 2 was made of
    audit_job = wait(g, admin, g.start_audit_form.sync(client=admin, body=audit_body, version=2, dedupe=True))
    assert audit_job.state == "succeeded", audit_job
    audit = g.get_audit.sync(audit_job.result["audit"], client=admin)
    assert isinstance(audit, m.AuditOut) and audit.version == 2

    again = m.UploadCalibrationOverrides(allow_duplicate=True, reason="the same batch again, on purpose")
    third = wait(
        g, admin, g.upload_calibration.sync(client=admin, body=File(**zip_file(whole)), overrides=again)
    )
    assert third.state == "succeeded" and third.version == 3, third
    no_reason = m.UploadCalibrationOverrides(force=True)
    refused = g.upload_calibration.sync_detailed(
        client=admin, body=File(**zip_file(whole)), overrides=no_reason
    )
    assert "force needs a reason" in problem_of(refused, 422, g).detail

    problem_of(g.get_calibration.sync_detailed(999, client=admin), 404, g)
    huge = File(payload=BytesIO(b"\xff" * MAX_REQUEST_BYTES), file_name="big.jpg", mime_type="image/jpeg")
    too_big = m.PredictFormBody(image=huge, request=parameters(instances))
    problem_of(g.predict_form.sync_detailed(client=anyone, body=too_big), 413, g)
    gif = File(payload=BytesIO(b"GIF89a not a picture"), file_name="a.gif", mime_type="image/gif")
    not_an_image = m.PredictPngFormBody(image=gif, request=parameters(instances))
    problem_of(g.predict_png_form.sync_detailed(client=anyone, body=not_an_image), 415, g)
    invalid = g.predict.sync_detailed(client=anyone, body=as_json(image, instances, epsilon=2))
    assert problem_of(invalid, 422, g).errors
