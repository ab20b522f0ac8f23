"""Execution providers: the session runs on the ones asked for, and one this onnxruntime lacks is
refused with a line naming those it has (CPU-only here; the GPU case: docs/operations.md)."""

from __future__ import annotations

import onnxruntime as ort
import pytest

from service.detector.session import Detector, _check_providers_loaded, provider_entry, session_providers
from service.errors import InvalidInput
from service.infra.settings import DEFAULT_MODEL_DIR

CPU = "CPUExecutionProvider"


def missing_provider() -> str:
    """A provider onnxruntime knows of but this build lacks (CUDA on a CPU build, say)."""
    lacking = [name for name in ort.get_all_providers() if name not in ort.get_available_providers()]
    assert lacking, f"this onnxruntime has every provider it knows: {ort.get_available_providers()}"
    return lacking[0]


def test_the_default_session_runs_on_the_cpu() -> None:
    assert Detector(DEFAULT_MODEL_DIR).execution_providers == [CPU]


def test_the_session_reports_the_providers_asked_for() -> None:
    detector = Detector(DEFAULT_MODEL_DIR, providers=[CPU], provider_options={CPU: {}})
    assert detector.execution_providers == [CPU]


def test_options_go_with_their_provider() -> None:
    assert session_providers([CPU], {CPU: {"device_id": "0"}}) == [(CPU, {"device_id": "0"})]
    assert session_providers([CPU], {}) == [CPU]


def test_cuda_runs_full_fp32_with_heuristic_algorithms_unless_told_otherwise() -> None:
    """TF32 would make the sets depend on the batch and drift from the calibration's fp32 scores."""
    cuda = "CUDAExecutionProvider"
    assert provider_entry(cuda, {}) == (cuda, {"use_tf32": "0", "cudnn_conv_algo_search": "HEURISTIC"})
    chosen = provider_entry(cuda, {"use_tf32": "1", "device_id": "1"})
    assert chosen == (cuda, {"use_tf32": "1", "cudnn_conv_algo_search": "HEURISTIC", "device_id": "1"})
    assert provider_entry(CPU, {}) == CPU


def test_an_unknown_provider_is_refused_naming_the_available_ones() -> None:
    with pytest.raises(InvalidInput) as refused:
        Detector(DEFAULT_MODEL_DIR, providers=["NoSuchExecutionProvider", CPU])
    message = refused.value.detail
    assert "'NoSuchExecutionProvider' (CKS_EXECUTION_PROVIDERS) is not a provider of" in message
    assert f"available: {', '.join(ort.get_available_providers())}" in message
    assert "\n" not in message


def test_a_provider_this_build_lacks_is_refused() -> None:
    name = missing_provider()
    with pytest.raises(InvalidInput) as refused:
        Detector(DEFAULT_MODEL_DIR, providers=[name, CPU])
    assert f"{name!r} (CKS_EXECUTION_PROVIDERS) is not available in this onnxruntime" in refused.value.detail
    assert CPU in refused.value.detail


def test_options_for_a_provider_not_asked_for_are_refused() -> None:
    with pytest.raises(InvalidInput, match="options for 'CUDAExecutionProvider', which is not in"):
        session_providers([CPU], {"CUDAExecutionProvider": {"device_id": "0"}})


def test_a_provider_that_fell_back_to_the_cpu_is_refused() -> None:
    """onnxruntime-gpu without a usable GPU loads the session on the CPU with only a log line."""
    refused = "CUDAExecutionProvider .* failed to load: the session runs on CPUExecutionProvider only"
    with pytest.raises(InvalidInput, match=refused):
        _check_providers_loaded(["CUDAExecutionProvider", CPU], [CPU])
    _check_providers_loaded([CPU], [CPU])
