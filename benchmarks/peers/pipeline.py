"""The model, its preprocessing and its sets, built from the service's own domain functions.

Decode (``service.detector.images``), crop (``service.detector.preprocess``), the onnxruntime
session (``service.detector.session.create_session``, on ``CKS_EXECUTION_PROVIDERS``), the
bundled calibration's thresholds (``service.calibration``) and the sets
(``service.prediction.calibrated_sets``): a peer only adds its framework around these, as a user
would, so its answers equal the service's.
"""

from __future__ import annotations

import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

from benchmarks.peers.accelerator import execution_providers
from service.calibration.bundle import BUNDLE_FILENAME, load_bundle
from service.calibration.registry import channel_thresholds
from service.detector.images import decode_image
from service.detector.manifest import MODEL_FILENAME, load_manifest
from service.detector.preprocess import build_batch
from service.detector.session import create_session, instance_heatmaps
from service.infra.settings import DEFAULT_MODEL_DIR
from service.prediction import calibrated_sets

#: the README's request: ``cov`` sets, keypoint coverage, epsilon 0.1
KIND, SCOPE, EPSILON = "cov", "keypoint", 0.1
MAX_PIXELS = 40_000_000


@dataclass(frozen=True)
class Prepared:
    """One request after decoding and cropping, before inference."""

    batch: np.ndarray  # (N, C, H, W) crops
    affines: np.ndarray  # (N, 2, 3)
    objects: list[str]


class Pipeline:
    """Decode + crop, inference, sets: split so that a framework can batch the middle step."""

    def __init__(self, model_dir: Path = DEFAULT_MODEL_DIR, intra_op_threads: int = 0) -> None:
        model_dir = Path(model_dir)
        self.manifest = load_manifest(model_dir)
        self.session = create_session(model_dir / MODEL_FILENAME, intra_op_threads, *execution_providers())
        _, table = load_bundle(model_dir / BUNDLE_FILENAME)
        self.thresholds = channel_thresholds(
            table, self.manifest.num_keypoints, KIND, SCOPE, EPSILON, None
        ).values

    def prepare(self, image: bytes, request: str | bytes | dict) -> Prepared:
        """``request``: the service's predict parameters (JSON text, or already parsed)."""
        instances = (request if isinstance(request, dict) else json.loads(request))["instances"]
        boxes = np.array([instance["bbox"] for instance in instances], dtype=np.float64)
        batch, affines = build_batch(decode_image(image, MAX_PIXELS), boxes, self.manifest)
        return Prepared(batch, affines, [instance["object"] for instance in instances])

    def infer(self, batch: np.ndarray) -> np.ndarray:
        feed = {self.manifest.input.name: batch}
        return self.session.run([self.manifest.output.name], feed)[0]

    def answer(self, prepared: Prepared, heatmaps: np.ndarray) -> dict:
        """Centres and shape matrices ((y - c)^T L (y - c) <= 1) per instance, in image pixels."""
        result = instance_heatmaps(self.manifest, heatmaps, prepared.objects, prepared.affines)
        sets = calibrated_sets(result, KIND, self.thresholds, self.manifest.heatmap)
        instances: list[dict] = [{"object": name, "keypoints": []} for name in prepared.objects]
        for row, owner in enumerate(result.instance_index):
            instances[owner]["keypoints"].append(
                {
                    "index": int(result.channel[row]),
                    "point": sets.centers[row].tolist(),
                    "shape_matrix": sets.shapes[row].tolist(),
                }
            )
        return {"instances": instances}

    def __call__(self, image: bytes, request: str | bytes | dict) -> dict:
        prepared = self.prepare(image, request)
        return self.answer(prepared, self.infer(prepared.batch))

    def infer_many(self, prepared: list[Prepared]) -> list[np.ndarray]:
        """One run for the crops of several requests; each gets its own slice back."""
        heatmaps = self.infer(np.concatenate([p.batch for p in prepared]))
        bounds = np.cumsum([len(p.batch) for p in prepared])[:-1]
        return np.split(heatmaps, bounds)
