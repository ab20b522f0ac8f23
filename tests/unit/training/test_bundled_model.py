"""The committed detector: manifest validates, matches the ONNX graph, and the sample is usable."""

from __future__ import annotations

import json
from pathlib import Path

import numpy as np
import onnx
import onnxruntime as ort

from service.detector.manifest import MODEL_FILENAME, load_manifest
from service.detector.preprocess import build_batch

MODEL_DIR = Path(__file__).resolve().parents[3] / "models" / "lmo-synth-unet"


def _dims(value_info: onnx.ValueInfoProto) -> list:
    return [d.dim_param or d.dim_value for d in value_info.type.tensor_type.shape.dim]


def test_manifest_matches_the_onnx_graph() -> None:
    manifest = load_manifest(MODEL_DIR)
    path = MODEL_DIR / MODEL_FILENAME
    assert path.stat().st_size <= 10 * 1024 * 1024
    graph = onnx.load(str(path)).graph
    assert not any(t.data_location == onnx.TensorProto.EXTERNAL for t in graph.initializer)
    (inp,), (out,) = graph.input, graph.output
    assert inp.name == manifest.input.name and out.name == manifest.output.name
    assert _dims(inp)[1:] == [manifest.input.channels, manifest.input.height, manifest.input.width]
    assert _dims(out)[1:] == [manifest.num_keypoints, manifest.output.height, manifest.output.width]
    assert isinstance(_dims(inp)[0], str), "batch axis must be dynamic"
    session = ort.InferenceSession(str(path), providers=["CPUExecutionProvider"])
    batch = np.zeros((3, manifest.input.channels, manifest.input.height, manifest.input.width), np.float32)
    (heatmaps,) = session.run([manifest.output.name], {manifest.input.name: batch})
    assert heatmaps.shape == (3, manifest.num_keypoints, manifest.output.height, manifest.output.width)


def test_manifest_is_what_the_training_code_builds() -> None:
    from training.manifest import build_manifest

    committed = load_manifest(MODEL_DIR)
    assert committed == build_manifest(MODEL_DIR.name, top_k=committed.heatmap.top_k)


def test_sample_is_small_and_complete() -> None:
    import cv2

    samples = MODEL_DIR / "samples"
    coco = json.loads((samples / "annotations.json").read_text())
    assert 10 <= len(coco["images"]) <= 20
    total = sum(f.stat().st_size for f in samples.rglob("*") if f.is_file())
    assert total < 3 * 1024 * 1024
    manifest = load_manifest(MODEL_DIR)
    assert {c["name"] for c in coco["categories"]} <= set(manifest.object_names)
    im = coco["images"][0]
    image = cv2.imread(str(samples / im["file_name"]))
    boxes = np.array([a["bbox"] for a in coco["annotations"] if a["image_id"] == im["id"]])
    batch, affines = build_batch(image, boxes, manifest)
    assert batch.shape[0] == len(boxes) == affines.shape[0]
