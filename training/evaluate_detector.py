"""Point-estimate accuracy of an ONNX detector on a COCO keypoints split, with ground-truth boxes.

    python -m training.evaluate_detector --data data/lmo_synth/test --model models/lmo-synth-unet

Crops go through the service's ``build_batch``. The point estimate of a keypoint is
the ``point`` the service returns for the nonconformity function ``--point``: for
``peak`` (the default) the centre of the argmax pixel, the detector's own estimate;
for ``var``/``cov`` the top-K weighted mean of the normalized heatmap (normalization
and K from the manifest). It is mapped back to the image by the inverse of the
image->heatmap affine. Errors are normalized by max(box w, h); PCK uses 0.05.
"""

from __future__ import annotations

import argparse
import json
from collections.abc import Iterator
from dataclasses import dataclass
from pathlib import Path

import cv2
import numpy as np
import onnxruntime as ort
from tqdm import tqdm

from service.conformal import point_estimates
from service.detector.crop import apply_affines, invert_affines
from service.detector.manifest import MODEL_FILENAME, Manifest, load_manifest
from service.detector.preprocess import build_batch
from training.coco import ANNOTATIONS_FILENAME, read_coco

PCK_THRESHOLD = 0.05
POINT_KINDS = ("peak", "var", "cov")


@dataclass(frozen=True)
class ImageInstances:
    """The detector's heatmaps of every annotated instance of one image, with its labels."""

    heatmaps: np.ndarray  # (n, 8, H, W): each instance's own object channels
    affines: np.ndarray  # (n, 2, 3) image -> heatmap
    labels: np.ndarray  # (n, 8, 3) COCO x, y, v
    boxes: np.ndarray  # (n, 4) x, y, w, h
    objects: list[str]


def image_instances(
    data: Path, model_dir: Path, max_images: int | None = None, desc: str = "evaluate"
) -> Iterator[ImageInstances]:
    """Run the detector on the ground-truth boxes of every image of a COCO split."""
    manifest = load_manifest(model_dir)
    session = ort.InferenceSession(str(Path(model_dir) / MODEL_FILENAME), providers=["CPUExecutionProvider"])
    coco = read_coco(Path(data) / ANNOTATIONS_FILENAME)
    names = {c["id"]: c["name"] for c in coco["categories"]}
    by_image: dict[int, list[dict]] = {}
    for ann in coco["annotations"]:
        by_image.setdefault(ann["image_id"], []).append(ann)
    for im in tqdm(coco["images"][:max_images], desc=desc, mininterval=10):
        anns = by_image.get(im["id"], [])
        if not anns:
            continue
        image = cv2.imread(str(Path(data) / im["file_name"]), cv2.IMREAD_COLOR)
        boxes = np.array([a["bbox"] for a in anns], dtype=np.float64)
        objects = [names[a["category_id"]] for a in anns]
        batch, affines = build_batch(image, boxes, manifest)
        (heatmaps,) = session.run([manifest.output.name], {manifest.input.name: batch})
        channels = np.array([manifest.object(name).keypoints for name in objects])
        yield ImageInstances(
            heatmaps=np.take_along_axis(heatmaps, channels[:, :, None, None], axis=1),
            affines=affines,
            labels=np.array([a["keypoints"] for a in anns], dtype=np.float64).reshape(len(anns), -1, 3),
            boxes=boxes,
            objects=objects,
        )


def service_points(heatmaps: np.ndarray, manifest: Manifest, kind: str = "peak") -> np.ndarray:
    """The service's point estimates ``(n, K, 2)`` in heatmap coordinates for heatmaps ``(n, K, H, W)``."""
    n, k, h, w = heatmaps.shape
    spec = manifest.heatmap
    flat = heatmaps.reshape(n * k, h, w)
    return point_estimates(kind, flat, spec.normalization, spec.top_k, spec.temperature).reshape(n, k, 2)


def collect_errors(
    data: Path, model_dir: Path, max_images: int | None = None, kind: str = "peak"
) -> dict[str, np.ndarray]:
    """Normalized errors, visibility flags and object names of every labelled keypoint."""
    manifest = load_manifest(model_dir)
    errors, flags, objects = [], [], []
    for found in image_instances(data, model_dir, max_images):
        points = apply_affines(invert_affines(found.affines), service_points(found.heatmaps, manifest, kind))
        scale = np.maximum(found.boxes[:, 2], found.boxes[:, 3])[:, None]
        errors.append((np.linalg.norm(points - found.labels[:, :, :2], axis=2) / scale).ravel())
        flags.append(found.labels[:, :, 2].ravel())
        objects += [o for o in found.objects for _ in range(found.labels.shape[1])]
    return {"error": np.concatenate(errors), "v": np.concatenate(flags), "object": np.array(objects)}


def summarize(errors: np.ndarray) -> dict[str, float]:
    if len(errors) == 0:
        return {"count": 0, "pck": float("nan"), "median": float("nan")}
    return {
        "count": int(len(errors)),
        "pck": float((errors <= PCK_THRESHOLD).mean()),
        "median": float(np.median(errors)),
    }


def report(result: dict[str, np.ndarray]) -> dict[str, dict]:
    out: dict[str, dict] = {}
    for label, v in (("visible", 2), ("occluded", 1)):
        mask = result["v"] == v
        out[label] = summarize(result["error"][mask])
        out[label]["per_object"] = {
            name: summarize(result["error"][mask & (result["object"] == name)])
            for name in sorted(set(result["object"].tolist()))
        }
    return out


def format_report(summary: dict[str, dict]) -> str:
    lines = ["| keypoints | count | PCK@0.05 | median error / max(w,h) |", "|---|---|---|---|"]
    for label, s in summary.items():
        lines.append(f"| {label} (all) | {s['count']} | {s['pck']:.3f} | {s['median']:.4f} |")
        for name, o in s["per_object"].items():
            lines.append(f"| {label} {name} | {o['count']} | {o['pck']:.3f} | {o['median']:.4f} |")
    return "\n".join(lines)


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--data", type=Path, required=True)
    parser.add_argument("--model", type=Path, required=True, help="model directory (onnx + manifest)")
    parser.add_argument(
        "--point",
        choices=POINT_KINDS,
        default="peak",
        help="evaluate the service's point for this nonconformity function",
    )
    parser.add_argument("--max-images", type=int, default=None)
    parser.add_argument("--json", type=Path, default=None, help="also write the summary as JSON")
    args = parser.parse_args(argv)
    summary = report(collect_errors(args.data, args.model, args.max_images, args.point))
    print(f"point estimate: the service's {args.point!r} point")
    print(format_report(summary))
    if args.json:
        args.json.write_text(json.dumps({"point": args.point, **summary}, indent=2))


if __name__ == "__main__":
    main()
