"""Point-estimate accuracy of an ONNX detector on a COCO keypoints split, with ground-truth boxes.

    python -m training.evaluate_detector --data data/lmo_synth/test --model models/lmo-synth-unet

Crops go through the service's ``build_batch``; the point estimate of a keypoint is the
centre of the argmax pixel of its channel, mapped back to the image by the inverse of
the image->heatmap affine. Errors are normalized by max(box w, h); PCK uses 0.05.
"""

from __future__ import annotations

import argparse
import json
from pathlib import Path

import cv2
import numpy as np
import onnxruntime as ort
from tqdm import tqdm

from service.detector.crop import apply_affines, invert_affines
from service.detector.manifest import MODEL_FILENAME, Manifest, load_manifest
from service.detector.preprocess import build_batch
from training.coco import ANNOTATIONS_FILENAME, read_coco

PCK_THRESHOLD = 0.05


def argmax_points(heatmaps: np.ndarray) -> np.ndarray:
    """``(N, K, H, W)`` -> ``(N, K, 2)`` centres ``(c + 0.5, r + 0.5)`` of the argmax pixels."""
    n, k, h, w = heatmaps.shape
    flat = heatmaps.reshape(n, k, -1).argmax(axis=2)
    return np.stack([flat % w + 0.5, flat // w + 0.5], axis=2).astype(np.float64)


def predict_image(session: ort.InferenceSession, manifest: Manifest, image_bgr: np.ndarray, boxes: np.ndarray,
                  objects: list[str]) -> np.ndarray:
    """Image-space point estimates ``(N, 8, 2)`` for boxes of the given objects."""
    batch, affines = build_batch(image_bgr, boxes, manifest)
    (heatmaps,) = session.run([manifest.output.name], {manifest.input.name: batch})
    channels = np.array([manifest.object(name).keypoints for name in objects])
    picked = np.take_along_axis(heatmaps, channels[:, :, None, None], axis=1)
    return apply_affines(invert_affines(affines), argmax_points(picked))


def collect_errors(data: Path, model_dir: Path, max_images: int | None = None) -> dict[str, np.ndarray]:
    """Normalized errors, visibility flags and object names of every labelled keypoint."""
    manifest = load_manifest(model_dir)
    session = ort.InferenceSession(str(Path(model_dir) / MODEL_FILENAME), providers=["CPUExecutionProvider"])
    coco = read_coco(Path(data) / ANNOTATIONS_FILENAME)
    names = {c["id"]: c["name"] for c in coco["categories"]}
    by_image: dict[int, list[dict]] = {}
    for ann in coco["annotations"]:
        by_image.setdefault(ann["image_id"], []).append(ann)
    errors, flags, objects = [], [], []
    for im in tqdm(coco["images"][:max_images], desc="evaluate", mininterval=10):
        anns = by_image.get(im["id"], [])
        if not anns:
            continue
        image = cv2.imread(str(Path(data) / im["file_name"]), cv2.IMREAD_COLOR)
        boxes = np.array([a["bbox"] for a in anns], dtype=np.float64)
        objs = [names[a["category_id"]] for a in anns]
        pred = predict_image(session, manifest, image, boxes, objs)
        gt = np.array([a["keypoints"] for a in anns], dtype=np.float64).reshape(len(anns), -1, 3)
        scale = np.maximum(boxes[:, 2], boxes[:, 3])[:, None]
        errors.append((np.linalg.norm(pred - gt[:, :, :2], axis=2) / scale).ravel())
        flags.append(gt[:, :, 2].ravel())
        objects += [o for o in objs for _ in range(gt.shape[1])]
    return {"error": np.concatenate(errors), "v": np.concatenate(flags), "object": np.array(objects)}


def summarize(errors: np.ndarray) -> dict[str, float]:
    if len(errors) == 0:
        return {"count": 0, "pck": float("nan"), "median": float("nan")}
    return {"count": int(len(errors)), "pck": float((errors <= PCK_THRESHOLD).mean()),
            "median": float(np.median(errors))}


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
    parser.add_argument("--max-images", type=int, default=None)
    parser.add_argument("--json", type=Path, default=None, help="also write the summary as JSON")
    args = parser.parse_args(argv)
    summary = report(collect_errors(args.data, args.model, args.max_images))
    print(format_report(summary))
    if args.json:
        args.json.write_text(json.dumps(summary, indent=2))


if __name__ == "__main__":
    main()
