"""The ONNX detector: load a model directory, check it against its manifest, run batches."""

from __future__ import annotations

import hashlib
import os
import threading
import time
from collections.abc import Iterator, Mapping, Sequence
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path

import numpy as np
import onnxruntime as ort

from service.detector.frames import ImageSource
from service.detector.manifest import MODEL_FILENAME, Manifest, ManifestError, load_manifest
from service.detector.preprocess import build_batch
from service.errors import InvalidInput
from service.infra.metrics import BATCH_SIZE, INFERENCE_SECONDS

CPU = ("CPUExecutionProvider",)
#: Options the service gives a provider unless CKS_EXECUTION_PROVIDER_OPTIONS says otherwise.
#: CUDA: TF32 convolutions (onnxruntime's default) move the heatmaps by about 1e-3 of their
#: range, and differently for each batch size, so a request's sets would depend on the requests
#: it was merged with and drift from the calibration's fp32 scores; cuDNN's exhaustive algorithm
#: search (the default) stalls the first run of every new batch size for 0.2-0.7 s (measured on
#: an H200, docs/operations.md "Execution providers and GPUs").
PROVIDER_DEFAULTS: dict[str, dict[str, str]] = {
    "CUDAExecutionProvider": {"use_tf32": "0", "cudnn_conv_algo_search": "HEURISTIC"},
}


class ModelMismatch(Exception):
    """The model directory cannot be served: the message names what does not fit."""


def file_sha256(path: Path, chunk: int = 1 << 20) -> str:
    digest = hashlib.sha256()
    with open(path, "rb") as handle:
        while block := handle.read(chunk):
            digest.update(block)
    return digest.hexdigest()


@dataclass(frozen=True)
class InstanceHeatmaps:
    """Heatmaps of one request, flattened to one row per (instance, keypoint of its object)."""

    heatmaps: np.ndarray  # (M, H, W) float32 raw network output
    instance_index: np.ndarray  # (M,) which instance each row belongs to
    channel: np.ndarray  # (M,) manifest keypoint index of each row
    affines: np.ndarray  # (N, 2, 3) image -> heatmap affine per instance


class Detector:
    """A validated ONNX heatmap model and its manifest; ``run`` is thread-safe.

    One rule for threads: a request alone in the process runs on every usable core, and while
    others compute too, each run has ``threads`` intra-op threads (concurrent runs in parallel).
    """

    def __init__(
        self,
        model_dir: Path,
        threads: int = 0,
        *,
        providers: Sequence[str] = CPU,
        provider_options: Mapping[str, Mapping[str, str]] | None = None,
    ) -> None:
        """``threads``: onnxruntime intra-op threads of a run beside others (0: onnxruntime's
        default, every run). A lone request's session exists on the CPU provider only."""
        model_dir = Path(model_dir)
        self.manifest = _load_manifest(model_dir)
        model_path = model_dir / MODEL_FILENAME
        if not model_path.is_file():
            raise ModelMismatch(f"{model_path} does not exist")
        self.model_hash = file_sha256(model_path)
        _check_variant(self.manifest, self.model_hash, providers)
        # No busy-waiting between runs: a spinning intra-op thread holds a core that the request's
        # decode, its event loop and other requests need (bench_ab: half the server's core-ms).
        self._session = create_session(model_path, threads, providers, provider_options, spinning=False)
        cores = usable_cores()
        alone = threads != 0 and cores > threads and tuple(providers) == CPU
        # A lone request's threads spin between the pieces of its run, so the other cores stay awake
        # for it (after an idle gap a halted core is slow to wake); beside others they sleep.
        self._alone_session = create_session(model_path, cores) if alone else None
        self.alone_threads = cores if alone else threads
        self._computing, self._counting = 0, threading.Lock()
        _check_graph(self._session, self.manifest)
        self._check_output_shape()

    @property
    def execution_providers(self) -> list[str]:
        """The providers the session really runs on, in onnxruntime's order of preference."""
        return self._session.get_providers()

    @contextmanager
    def computing(self) -> Iterator[None]:
        """One request being computed in this process (decode to sets): while it is the only one,
        its run takes every usable core."""
        with self._counting:
            self._computing += 1
        try:
            yield
        finally:
            with self._counting:
                self._computing -= 1

    def run(self, batch: np.ndarray) -> np.ndarray:
        """``(N, C, H, W)`` float32 input -> ``(N, K, h, w)`` float32 heatmaps, in one run on this
        thread (concurrent requests run in parallel on their own threads)."""
        spec = self.manifest
        alone = self._alone_session is not None and self._computing <= 1
        session = self._alone_session if alone else self._session
        started = time.perf_counter()
        heatmaps = session.run([spec.output.name], {spec.input.name: batch})[0]
        INFERENCE_SECONDS.observe(time.perf_counter() - started)
        BATCH_SIZE.observe(len(batch))
        return heatmaps

    def infer(
        self, image: np.ndarray | ImageSource, boxes: np.ndarray, objects: list[str]
    ) -> InstanceHeatmaps:
        """Crop all boxes of ``image`` (pixels, or a frame's source), run them as one batch, keep
        each instance's own keypoint channels."""
        batch, affines = build_batch(image, boxes, self.manifest)
        return instance_heatmaps(self.manifest, self.run(batch), objects, affines)

    def _check_output_shape(self) -> None:
        spec = self.manifest.input
        probe = np.zeros((2, spec.channels, spec.height, spec.width), dtype=np.float32)
        try:
            out = self.run(probe)
        except Exception as error:  # onnxruntime raises its own untyped errors
            raise ModelMismatch(f"the model does not run on a manifest-shaped input: {error}") from error
        expected = (2, self.manifest.num_keypoints, self.manifest.output.height, self.manifest.output.width)
        if out.shape != expected:
            raise ModelMismatch(
                f"output {self.manifest.output.name!r} has shape {tuple(out.shape)} for a batch of 2, "
                f"but the manifest implies {expected} (batch, keypoints, output.height, output.width)"
            )


def usable_cores(cpu_max: Path = Path("/sys/fs/cgroup/cpu.max")) -> int:
    """The cores this process may run on: its CPU affinity, capped by a cgroup v2 CPU quota (a
    container limited to 2 CPUs on a 64-core node can use 2)."""
    cores = len(os.sched_getaffinity(0))
    try:
        quota, period = cpu_max.read_text().split()[:2]
    except (OSError, ValueError):
        return cores
    return cores if quota == "max" else max(1, min(cores, int(quota) // int(period)))


def instance_heatmaps(
    manifest: Manifest, heatmaps: np.ndarray, objects: list[str], affines: np.ndarray
) -> InstanceHeatmaps:
    """The rows of a batch's ``(N, K, h, w)`` output that matter: each instance's own keypoints."""
    channels = [np.asarray(manifest.object(name).keypoints) for name in objects]
    instance_index = np.concatenate([np.full(len(c), i) for i, c in enumerate(channels)])
    channel = np.concatenate(channels)
    return InstanceHeatmaps(heatmaps[instance_index, channel], instance_index, channel, affines)


def _load_manifest(model_dir: Path) -> Manifest:
    try:
        return load_manifest(model_dir)
    except FileNotFoundError as error:
        raise ModelMismatch(f"no manifest.json in {model_dir}") from error
    except ManifestError as error:
        raise ModelMismatch(str(error)) from error


def create_session(
    model_path: Path,
    intra_op_threads: int,
    providers: Sequence[str] = CPU,
    provider_options: Mapping[str, Mapping[str, str]] | None = None,
    *,
    spinning: bool = True,
) -> ort.InferenceSession:
    """The onnxruntime session the service runs: sequential, all graph optimizations, on
    ``providers`` (checked by ``session_providers``); ``spinning``: whether its intra-op threads
    busy-wait for work after each piece of a run (onnxruntime's default) or sleep."""
    options = ort.SessionOptions()
    options.intra_op_num_threads = intra_op_threads
    if not spinning:
        options.add_session_config_entry("session.intra_op.allow_spinning", "0")
    options.inter_op_num_threads = 1
    options.execution_mode = ort.ExecutionMode.ORT_SEQUENTIAL
    options.graph_optimization_level = ort.GraphOptimizationLevel.ORT_ENABLE_ALL
    chosen = session_providers(providers, provider_options or {})
    try:
        session = ort.InferenceSession(str(model_path), options, providers=chosen)
    except Exception as error:
        raise ModelMismatch(f"onnxruntime cannot load {model_path}: {error}") from error
    _check_providers_loaded(providers, session.get_providers())
    return session


def session_providers(
    names: Sequence[str], options: Mapping[str, Mapping[str, str]]
) -> list[str | tuple[str, dict[str, str]]]:
    """onnxruntime's ``providers`` argument; a provider this onnxruntime lacks is refused (one line)."""
    available = ort.get_available_providers()
    listed = ", ".join(available)
    for name in names:
        if name not in available:
            kind = "is not available in" if name in ort.get_all_providers() else "is not a provider of"
            raise InvalidInput(
                f"execution provider {name!r} (CKS_EXECUTION_PROVIDERS) {kind} this onnxruntime"
                f" {ort.__version__}; available: {listed} (GPU: docs/operations.md, Execution providers)"
            )
    for name in options:
        if name not in names:
            raise InvalidInput(
                f"CKS_EXECUTION_PROVIDER_OPTIONS has options for {name!r}, which is not in"
                f" CKS_EXECUTION_PROVIDERS ({', '.join(names)})"
            )
    return [provider_entry(name, options.get(name, {})) for name in names]


def provider_entry(name: str, options: Mapping[str, str]) -> str | tuple[str, dict[str, str]]:
    """One item of onnxruntime's ``providers``: the name, with its options over ``PROVIDER_DEFAULTS``."""
    merged = {**PROVIDER_DEFAULTS.get(name, {}), **options}
    return (name, merged) if merged or name in PROVIDER_DEFAULTS else name


def _check_providers_loaded(requested: Sequence[str], in_use: list[str]) -> None:
    """onnxruntime falls back to CPU, with only a log line, when e.g. CUDA's libraries or device
    are missing: a GPU setting that silently runs on the CPU is refused instead."""
    missing = [name for name in requested if name not in in_use]
    if missing:
        raise InvalidInput(
            f"execution provider(s) {', '.join(missing)} (CKS_EXECUTION_PROVIDERS) failed to load:"
            f" the session runs on {', '.join(in_use)} only (onnxruntime's log above says why)"
        )


def _check_variant(manifest: Manifest, model_hash: str, providers: Sequence[str]) -> None:
    """The variant an answer names is the one that runs: its manifest names this model.onnx."""
    variant = manifest.variant
    if variant is None:
        return
    if variant.model_sha256 != model_hash:
        raise ModelMismatch(
            f"manifest.json names the {variant.name} variant of model.onnx {variant.model_sha256[:12]}, but"
            f" model.onnx here is {model_hash[:12]}: keep the folder `keypoint-service optimize` wrote whole"
        )
    if variant.name == "float16" and tuple(providers) == CPU:
        raise ModelMismatch(
            "a float16 variant runs on a GPU execution provider (CKS_EXECUTION_PROVIDERS); on CPUs serve"
            f" its source {variant.source_name!r} or an int8 variant"
        )


def _check_graph(session: ort.InferenceSession, manifest: Manifest) -> None:
    inputs = {i.name: i for i in session.get_inputs()}
    outputs = {o.name: o for o in session.get_outputs()}
    if manifest.input.name not in inputs:
        raise ModelMismatch(
            f"manifest input.name {manifest.input.name!r} is not a model input "
            f"(model inputs: {sorted(inputs)})"
        )
    if manifest.output.name not in outputs:
        raise ModelMismatch(
            f"manifest output.name {manifest.output.name!r} is not a model output "
            f"(model outputs: {sorted(outputs)})"
        )
    spec = manifest.input
    _check_dims("input", inputs[manifest.input.name].shape, (spec.channels, spec.height, spec.width))
    out = manifest.output
    _check_dims("output", outputs[out.name].shape, (manifest.num_keypoints, out.height, out.width))


def _check_dims(which: str, graph_shape: list, expected: tuple[int, ...]) -> None:
    names = ("channels" if which == "input" else "keypoints", "height", "width")
    if len(graph_shape) != 4:
        raise ModelMismatch(f"model {which} has rank {len(graph_shape)}, expected 4 (N, C, H, W)")
    for name, got, want in zip(names, graph_shape[1:], expected, strict=True):
        if isinstance(got, int) and got != want:
            raise ModelMismatch(f"model {which} {name} is {got} but the manifest says {want}")
