"""Bring your own model, worked example: a SimpleBaseline heatmap network exported to ONNX with its manifest.

    python docs/examples/export_simplebaseline.py --model-dir models/simplebaseline-demo

SimpleBaseline (Xiao, Wu and Wei, "Simple Baselines for Human Pose Estimation and
Tracking", ECCV 2018) is a ResNet backbone (output stride 32) followed by three 4x4
transposed convolutions with stride 2 and a 1x1 convolution: one heatmap per keypoint at
stride 4. Here the backbone is a small ResNet (one basic block per stage) so that it runs
quickly on a CPU, in plain torch. Nothing is downloaded: the weights are random (seeded),
which makes the prediction sets wide but leaves the conformal guarantee intact, since the
guarantee holds for any detector. ``load_model`` is where a checkpoint would be loaded.

The manifest differs from the bundled model's where real exports differ: a 256x192 (h x w)
input, BGR channel order with ImageNet statistics (in BGR order), 64x48 heatmaps, softmax
normalization with a temperature and its own top-K. Its objects and keypoints are the
bundled model's, so the bundled samples (a COCO-keypoints folder) can calibrate it.
See docs/bring-your-own-model.md for every step after this one.
"""

from __future__ import annotations

import argparse
from pathlib import Path

import torch
from torch import nn

from service.detector.manifest import (
    MODEL_FILENAME,
    HeatmapSpec,
    InputSpec,
    Manifest,
    OutputSpec,
    load_manifest,
)
from service.infra.settings import DEFAULT_MODEL_DIR
from training.export import export_onnx, max_difference
from training.manifest import IMAGENET_MEAN, IMAGENET_STD, write_manifest

INPUT_SIZE = (256, 192)  # height, width
HEATMAP_STRIDE = 4


class BasicBlock(nn.Module):
    """ResNet's basic block: two 3x3 convolutions and an identity (or 1x1 projected) shortcut."""

    def __init__(self, cin: int, cout: int, stride: int) -> None:
        super().__init__()
        self.body = nn.Sequential(
            nn.Conv2d(cin, cout, 3, stride, 1, bias=False),
            nn.BatchNorm2d(cout),
            nn.ReLU(inplace=True),
            nn.Conv2d(cout, cout, 3, 1, 1, bias=False),
            nn.BatchNorm2d(cout),
        )
        self.shortcut = (
            nn.Identity()
            if stride == 1 and cin == cout
            else nn.Sequential(nn.Conv2d(cin, cout, 1, stride, bias=False), nn.BatchNorm2d(cout))
        )

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return torch.relu(self.body(x) + self.shortcut(x))


class SimpleBaseline(nn.Module):
    """ResNet stem and four stages (stride 32), three stride-2 deconvolutions, a 1x1 head (stride 4)."""

    def __init__(
        self, num_keypoints: int, widths: tuple[int, ...] = (16, 32, 64, 128), deconv: int = 64
    ) -> None:
        super().__init__()
        stem = [
            nn.Conv2d(3, widths[0], 7, 2, 3, bias=False),
            nn.BatchNorm2d(widths[0]),
            nn.ReLU(inplace=True),
        ]
        inputs = (widths[0], *widths[:-1])
        stages = [
            BasicBlock(cin, cout, 1 if i == 0 else 2)
            for i, (cin, cout) in enumerate(zip(inputs, widths, strict=True))
        ]
        self.backbone = nn.Sequential(*stem, nn.MaxPool2d(3, 2, 1), *stages)
        layers: list[nn.Module] = []
        cin = widths[-1]
        for _ in range(3):
            layers += [
                nn.ConvTranspose2d(cin, deconv, 4, 2, 1, bias=False),
                nn.BatchNorm2d(deconv),
                nn.ReLU(True),
            ]
            cin = deconv
        self.deconv = nn.Sequential(*layers)
        self.head = nn.Conv2d(deconv, num_keypoints, 1)

    def forward(self, x: torch.Tensor) -> torch.Tensor:
        return self.head(self.deconv(self.backbone(x)))


def build_manifest(name: str) -> Manifest:
    """The example's manifest: its own input, output and heatmap settings, the bundled objects."""
    bundled = load_manifest(DEFAULT_MODEL_DIR)
    height, width = INPUT_SIZE
    return Manifest(
        name=name,
        input=InputSpec(
            name="input",
            height=height,
            width=width,
            color="BGR",
            scale=255.0,
            mean=IMAGENET_MEAN[::-1],  # a network trained on BGR crops (OpenCV order) lists them B, G, R
            std=IMAGENET_STD[::-1],
        ),
        output=OutputSpec(name="heatmaps", height=height // HEATMAP_STRIDE, width=width // HEATMAP_STRIDE),
        heatmap=HeatmapSpec(normalization="softmax", temperature=0.5, top_k=64),
        keypoints=bundled.keypoints,
        objects=bundled.objects,
    )


def load_model(num_keypoints: int, seed: int) -> SimpleBaseline:
    """The network with seeded random weights; a real export loads its checkpoint here instead:
    ``model.load_state_dict(torch.load(path, map_location="cpu"))``."""
    torch.manual_seed(seed)
    return SimpleBaseline(num_keypoints).eval()


def export(model_dir: Path, seed: int = 0) -> tuple[Path, float]:
    """Write model.onnx and manifest.json; returns the ONNX path and max |ORT - PyTorch| on random crops."""
    model_dir.mkdir(parents=True, exist_ok=True)
    manifest = build_manifest(model_dir.resolve().name)
    model = load_model(manifest.num_keypoints, seed)
    path = export_onnx(model, manifest, model_dir / MODEL_FILENAME)
    write_manifest(model_dir, manifest)
    spec = manifest.input
    crops = torch.randn(
        4, spec.channels, spec.height, spec.width, generator=torch.Generator().manual_seed(seed)
    )
    return path, max_difference(model, path, crops.numpy(), spec.name)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--model-dir", type=Path, required=True, help="where model.onnx and manifest.json go")
    parser.add_argument("--seed", type=int, default=0)
    args = parser.parse_args(argv)
    path, diff = export(args.model_dir, args.seed)
    print(f"wrote {path} ({path.stat().st_size / 1e6:.2f} MB) and {args.model_dir / 'manifest.json'}")
    print(f"onnxruntime vs PyTorch max |diff| on random crops: {diff:.1e}")


if __name__ == "__main__":
    main()
