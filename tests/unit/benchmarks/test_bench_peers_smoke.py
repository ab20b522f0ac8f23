"""Smoke test of benchmarks.bench_peers: each peer really serves the service's answer, the check
catches one that does not, and the report and page come out whole (timings are never asserted;
wrk is not needed here)."""

from __future__ import annotations

import copy
import os
from pathlib import Path

import onnxruntime
import pytest

from benchmarks.bench_peers import parse_args, use_gpu
from benchmarks.harness import BOXES, LoadResult, Machine, Requests, load_sample, write_section
from benchmarks.peers.accelerator import CUDA, GPU_SETTINGS
from benchmarks.peers.answers import difference
from benchmarks.peers.measure import CONCURRENCIES, AnswerMismatch, Runs, check_answers
from benchmarks.peers.profile import OTHER, summarize
from benchmarks.peers.report import PeerResults, goals, render
from benchmarks.peers.servers import PEERS, SERVICE, SERVICE_INT8, SERVICE_ON_GPU
from benchmarks.stages import Limit

PEER = {peer.name: peer for peer in PEERS}


@pytest.fixture(scope="module")
def requests(tmp_path_factory: pytest.TempPathFactory) -> Requests:
    return Requests.write(tmp_path_factory.mktemp("bodies"), load_sample())


@pytest.fixture(scope="module")
def service_answers(requests: Requests, tmp_path_factory: pytest.TempPathFactory) -> dict[int, dict]:
    with SERVICE.running(tmp_path_factory.mktemp("logs") / "service.log") as server:
        return check_answers(server.url, requests, {}, "original")


@pytest.mark.parametrize(
    "name", ["FastAPI", "LitServe", "BentoML", pytest.param("Ray Serve", marks=pytest.mark.ray)]
)
def test_the_peer_serves_the_services_answer(
    name: str, requests: Requests, service_answers: dict[int, dict], tmp_path: Path
) -> None:
    moved = copy.deepcopy(service_answers)
    moved[4]["instances"][3]["keypoints"][-1]["point"][1] += 1e-3
    with PEER[name].running(tmp_path / "peer.log") as server:
        answers = check_answers(server.url, requests, service_answers)  # raises on any difference
        with pytest.raises(AnswerMismatch, match="4 box"):
            check_answers(server.url, requests, moved)
    for boxes in BOXES:
        keypoints = [kp for instance in answers[boxes]["instances"] for kp in instance["keypoints"]]
        assert len(answers[boxes]["instances"]) == boxes and keypoints


def test_the_int8_variant_is_checked_on_its_own_answers(
    requests: Requests, service_answers: dict[int, dict], tmp_path: Path
) -> None:
    """Another model: float32's sets are not its reference; its own first answer and variant are."""
    with SERVICE_INT8.running(tmp_path / "int8.log") as server:
        first = check_answers(server.url, requests, {}, "int8")
        check_answers(server.url, requests, first, "int8")
        with pytest.raises(AnswerMismatch, match="model int8, not original"):
            check_answers(server.url, requests, first, "original")
    assert all(answer["model"]["variant"] == "int8" for answer in first.values())
    assert difference(service_answers[4], first[4]) is not None


def test_a_different_centre_or_shape_is_named(service_answers: dict[int, dict]) -> None:
    moved, stretched = copy.deepcopy(service_answers[1]), copy.deepcopy(service_answers[1])
    moved["instances"][0]["keypoints"][0]["point"][0] += 1e-3
    region = next(
        kp["set"] for kp in stretched["instances"][0]["keypoints"] if kp["set"]["type"] == "ellipse"
    )
    region["shape_matrix"][0][0] *= 1.001
    assert "centres differ" in (difference(service_answers[1], moved) or "")
    assert "shape matrices differ" in (difference(service_answers[1], stretched) or "")
    assert difference(service_answers[1], copy.deepcopy(service_answers[1])) is None


def _results() -> PeerResults:
    args = parse_args(["--quick", "--peers", "FastAPI,LitServe"])
    runs = Runs()
    for contender, speed in zip(args.contenders, (2.0, 3.0, 1.0, 1.5), strict=True):
        for boxes in BOXES:
            for concurrency in CONCURRENCIES:
                rate = 100.0 * speed / boxes
                result = LoadResult(concurrency, int(rate), 1.0, rate, 10.0 / speed, 20.0 / speed, 0, 0.01)
                runs.add(contender.name, (boxes, concurrency), result, cpu_seconds=result.requests * 0.005)
    stages = dict.fromkeys(("decode", "crop", "inference", "sets", "response", "json"), 1.0)
    limits = [Limit(n, 5.0 * n, 4.0 * n, 2, stages) for n in BOXES]
    machine = Machine(2, "test CPU", (0.5, 0.5, 0.5), "3.11", "1.0")
    return PeerResults(
        "python -m benchmarks.bench_peers --quick",
        machine,
        (1.0, 1.0, 1.0),
        1.0,
        1,
        args.contenders,
        runs,
        limits,
        1.0,
    )


def test_the_report_gives_goals_table_and_settings_and_keeps_bench_services_section(tmp_path: Path) -> None:
    results = _results()
    text = render(results)
    for heading in ("### Goals", "### Service and peers", "### Settings, and why", "### In-process limit"):
        assert heading in text
    assert results.peers == ["FastAPI", "LitServe"]  # the int8 variant is the service, not a peer
    assert len(goals(results)) == 11
    assert "| service | service int8 | FastAPI | LitServe | service / best peer | int8 / best peer |" in text
    # req/s: the service 2x FastAPI's speed, its int8 variant 3x, LitServe 1.5x
    assert "| **1.33** (LitServe) | **2.00** (LitServe) |" in text
    assert "4 box(es): service int8 / FastAPI | 0.33 (3.3 vs 10.0 ms) | 0.85 | met |" in text
    assert "- **service int8**: `CKS_MODEL_DIR=models/lmo-synth-unet-int8`" in text
    output = tmp_path / "performance.md"
    output.write_text(
        "# Performance\n\n<!-- bench_service:begin -->\nold figures\n<!-- bench_service:end -->\n"
    )
    write_section(output, "bench_peers", text)
    written = output.read_text()
    assert written.index("bench_peers:begin") < written.index("bench_service:begin")
    assert "\nold figures\n" in written and written.count("# Performance\n") == 1
    write_section(output, "bench_peers", text.replace("LitServe", "Litserve"))
    assert "Litserve" in output.read_text() and "old figures" in output.read_text()


def test_unknown_peers_are_refused() -> None:
    with pytest.raises(SystemExit):
        parse_args(["--peers", "Triton"])


def test_profile_samples_are_sorted_into_stages_and_waits_left_out() -> None:
    raw = "\n".join(
        [
            "thread (1);_worker (thread.py:81);_respond (predict.py:140);decode_image (images.py:120) 30",
            "thread (2);_worker (thread.py:81);Detector.run (session.py:70);"
            "Session.run (onnxruntime_inference_collection.py:406) 60",
            "thread (3);_worker (thread.py:81);Condition.wait (threading.py:320) 50",
            "thread (4);Runner.run (runners.py:118) 40",
            "thread (4);Runner.run (runners.py:118);RequestResponseCycle.send (httptools_impl.py:524) 10",
        ]
    )
    profile = summarize(raw)
    assert (profile.samples, profile.running) == (190, 100)
    assert profile.shares == {"inference (onnxruntime)": 0.6, "decode (JPEG)": 0.3, OTHER: 0.1}
    results = _results()
    section = render(PeerResults(**{**results.__dict__, "profile": profile}))
    assert "| inference (onnxruntime) | 60% |" in section


def test_worker_processes_samples_count_like_the_servers_own() -> None:
    """``--subprocesses`` puts a process frame first: the stage is found the same way."""
    raw = 'process 42:"python -m service.cli serve";thread (1);_worker (t.py:81);decode_image (i.py:1) 7'
    assert summarize(raw).shares == {"decode (JPEG)": 1.0}


def test_gpu_mode_runs_the_service_with_gpu_settings_into_its_own_section(tmp_path: Path) -> None:
    args = parse_args(["--gpu", "--peers", "FastAPI"])
    assert args.contenders[0] is SERVICE_ON_GPU and args.section == "bench_peers_gpu"
    assert SERVICE_INT8 not in args.contenders  # a CPU variant
    litserve = PEER["LitServe"]
    assert "accelerator='cuda'" in litserve.described(True) and litserve.described(False) == litserve.settings
    output = tmp_path / "performance.md"
    for section in ("bench_service", "bench_peers_gpu", "bench_peers"):
        write_section(output, section, f"## {section} text")
    written = output.read_text()
    assert (
        written.index("bench_peers text")
        < written.index("bench_peers_gpu text")
        < written.index("bench_service text")
    )


def test_gpu_mode_needs_the_cuda_provider(monkeypatch) -> None:
    """Without onnxruntime-gpu (CI) it stops naming what there is; with it, every server gets the
    GPU settings."""
    for name in GPU_SETTINGS:
        monkeypatch.delenv(name, raising=False)
    if CUDA not in onnxruntime.get_available_providers():
        with pytest.raises(SystemExit) as stopped:
            use_gpu()
        assert CUDA in str(stopped.value) and "CPUExecutionProvider" in str(stopped.value)
        assert "CKS_EXECUTION_PROVIDERS" not in os.environ
    else:
        use_gpu()
        assert os.environ["CKS_EXECUTION_PROVIDERS"].startswith(CUDA)
