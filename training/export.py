"""Export a checkpoint to ``models/<name>/model.onnx`` + ``manifest.json`` and check it.

    python -m training.export --checkpoint data/runs/lmo-synth-unet/last.pt \
        --model-dir models/lmo-synth-unet --check-data data/lmo_synth/test

The ONNX graph has a dynamic batch axis, input ``image`` (N, 3, 128, 128) and output
``heatmaps`` (N, K, 64, 64); the weights are embedded in the one file.
"""

from __future__ import annotations

import argparse
import warnings
from pathlib import Path

import numpy as np
import onnx
import onnxruntime as ort
import torch

from service.detector.manifest import MODEL_FILENAME, Manifest
from training.dataset import load_split, make_batch
from training.manifest import build_manifest, write_manifest
from training.model import HeatmapUNet
from training.train import load_checkpoint

OPSET = 17


def load_model(checkpoint: Path, manifest: Manifest) -> HeatmapUNet:
    model = HeatmapUNet(manifest.num_keypoints)
    load_checkpoint(checkpoint, model)
    return model.eval()


def export_onnx(model: torch.nn.Module, manifest: Manifest, path: Path) -> Path:
    spec = manifest.input
    dummy = torch.zeros(1, spec.channels, spec.height, spec.width)
    with warnings.catch_warnings():  # the TorchScript exporter is deprecated but needs no onnxscript
        warnings.simplefilter("ignore", DeprecationWarning)
        _export(model, dummy, path, manifest)
    graph_model = onnx.load(str(path))
    _static_output_shape(graph_model, manifest)
    onnx.checker.check_model(graph_model)
    onnx.save(graph_model, str(path))
    return path


def _static_output_shape(graph_model: onnx.ModelProto, manifest: Manifest) -> None:
    """Declare the heatmap dims (K, H, W) as fixed numbers; the exporter leaves them symbolic."""
    (output,) = graph_model.graph.output
    dims = output.type.tensor_type.shape.dim
    fixed = (manifest.num_keypoints, manifest.output.height, manifest.output.width)
    for dim, value in zip(dims[1:], fixed, strict=True):
        dim.Clear()
        dim.dim_value = value


def _export(model: torch.nn.Module, dummy: torch.Tensor, path: Path, manifest: Manifest) -> None:
    spec = manifest.input
    torch.onnx.export(
        model,
        (dummy,),
        str(path),
        input_names=[spec.name],
        output_names=[manifest.output.name],
        dynamic_axes={spec.name: {0: "batch"}, manifest.output.name: {0: "batch"}},
        opset_version=OPSET,
        dynamo=False,
    )


def max_difference(model: torch.nn.Module, onnx_path: Path, inputs: np.ndarray, input_name: str) -> float:
    """Largest absolute difference between PyTorch and onnxruntime heatmaps."""
    session = ort.InferenceSession(str(onnx_path), providers=["CPUExecutionProvider"])
    (onnx_out,) = session.run(None, {input_name: inputs})
    with torch.no_grad():
        torch_out = model(torch.from_numpy(inputs)).numpy()
    return float(np.abs(onnx_out - torch_out).max())


def real_crops(folder: Path, manifest: Manifest, count: int = 16) -> np.ndarray:
    """Un-augmented network inputs cut from the first images of a split."""
    split = load_split(folder, manifest, max_images=max(4, count // 2), progress=False)
    inputs, *_ = make_batch(split, np.arange(min(count, len(split))), manifest, rng=None)
    return inputs


def export(checkpoint: Path, model_dir: Path, check_data: Path | None = None) -> tuple[Path, float | None]:
    manifest = build_manifest(Path(model_dir).name)
    model_dir.mkdir(parents=True, exist_ok=True)
    model = load_model(checkpoint, manifest)
    path = export_onnx(model, manifest, model_dir / MODEL_FILENAME)
    write_manifest(model_dir, manifest)
    diff = None
    if check_data is not None:
        diff = max_difference(model, path, real_crops(check_data, manifest), manifest.input.name)
    return path, diff


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--checkpoint", type=Path, required=True)
    parser.add_argument("--model-dir", type=Path, required=True)
    parser.add_argument("--check-data", type=Path, default=None, help="split for the ORT vs PyTorch check")
    args = parser.parse_args(argv)
    path, diff = export(args.checkpoint, args.model_dir, args.check_data)
    print(f"wrote {path} ({path.stat().st_size / 1e6:.2f} MB)")
    if diff is not None:
        print(f"onnxruntime vs PyTorch max |diff| on real crops: {diff:.2e}")
        if diff > 1e-4:
            raise SystemExit("ONNX export does not match PyTorch within 1e-4")


if __name__ == "__main__":
    main()
