"""CKS_EXECUTION_PROVIDERS end to end: read as a list, reported by GET /v1/model and the start-up
log of the service (in process), and refused by `keypoint-service serve` (exit 2, one line naming the
providers this onnxruntime has) when it names one the machine lacks."""

from __future__ import annotations

from pathlib import Path

import onnxruntime as ort
import pytest
from pydantic import ValidationError

from benchmarks.load import predict, sample_request
from service.infra.settings import Settings
from tests.api.in_process import InProcess
from tests.cli_calls import assert_one_line_error, run
from tests.live.server import free_port
from tests.unit.detector.test_providers import missing_provider

CPU = "CPUExecutionProvider"
AVAILABLE = ", ".join(ort.get_available_providers())


@pytest.mark.parametrize(
    ("value", "expected"),
    [
        ("CPUExecutionProvider", (CPU,)),
        (" CUDAExecutionProvider , CPUExecutionProvider ", ("CUDAExecutionProvider", CPU)),
        ('["TensorrtExecutionProvider", "CPUExecutionProvider"]', ("TensorrtExecutionProvider", CPU)),
    ],
)
def test_the_setting_reads_a_comma_separated_or_json_list(monkeypatch, value: str, expected: tuple) -> None:
    monkeypatch.setenv("CKS_EXECUTION_PROVIDERS", value)
    assert Settings().model.execution_providers == expected


@pytest.mark.parametrize(
    ("value", "message"),
    [
        (" , ", "name at least one"),
        ("[]", "name at least one"),
        ('["CPU', "not a JSON list"),
        (f"{CPU},{CPU}", "named twice"),
    ],
)
def test_an_empty_or_malformed_list_is_refused(monkeypatch, value: str, message: str) -> None:
    monkeypatch.setenv("CKS_EXECUTION_PROVIDERS", value)
    with pytest.raises(ValidationError, match=message):
        Settings()


def test_the_defaults_keep_todays_behaviour(monkeypatch) -> None:
    for name in ("CKS_EXECUTION_PROVIDERS", "CKS_EXECUTION_PROVIDER_OPTIONS"):
        monkeypatch.delenv(name, raising=False)
    settings = Settings()
    assert settings.model.execution_providers == (CPU,)
    assert settings.model.execution_provider_options == {}


def test_the_server_reports_and_logs_the_providers_in_use(tmp_path: Path) -> None:
    image, instances = sample_request()
    settings = {"execution_providers": f'["{CPU}"]'}
    with InProcess(tmp_path / "data", **settings) as server:
        info = server.client.get("/v1/model")
        answer = predict(server.client, image, instances)
        log = server.log()
    assert info.status_code == 200 and info.json()["execution_providers"] == [CPU]
    assert answer.status_code == 200, answer.text
    assert f"onnxruntime execution providers in use: {CPU}" in log


@pytest.mark.parametrize(
    ("settings", "fragments"),
    [
        (
            {"execution_providers": f"NoSuchExecutionProvider,{CPU}"},
            [
                "'NoSuchExecutionProvider' (CKS_EXECUTION_PROVIDERS) is not a provider of",
                f"available: {AVAILABLE}",
            ],
        ),
        (
            {"execution_providers": f"{missing_provider()},{CPU}"},
            [f"'{missing_provider()}' (CKS_EXECUTION_PROVIDERS) is not available", f"available: {AVAILABLE}"],
        ),
        (
            {"execution_provider_options": '{"CUDAExecutionProvider": {"device_id": "1"}}'},
            ["CKS_EXECUTION_PROVIDER_OPTIONS has options for 'CUDAExecutionProvider'"],
        ),
        ({"execution_providers": "[CPU"}, ["invalid settings: CKS_EXECUTION_PROVIDERS: not a JSON list"]),
    ],
)
def test_serve_refuses_providers_this_machine_lacks(tmp_path: Path, settings: dict, fragments: list) -> None:
    result = run(["serve", "--port", str(free_port())], tmp_path / "data", **settings)
    assert_one_line_error(result, 2, *fragments)


def test_ray_replicas_reserve_gpus_only_when_asked() -> None:
    from service.deploy_ray import Scaling

    with_gpu = Scaling(num_gpus=1).deployment_options(Settings())
    assert with_gpu["ray_actor_options"] == {"num_cpus": 1, "num_gpus": 1}
    assert Scaling().deployment_options(Settings())["ray_actor_options"] == {"num_cpus": 1}
    with pytest.raises(ValueError, match="num_gpus must be 0 or more"):
        Scaling(num_gpus=-1)
