"""Choose the manifest's top-K (used by var and cov) on a held-out validation split.

    python -m training.select_top_k --data data/lmo_synth/validation --model models/lmo-synth-unet --write

The paper's K = 100 of 64x64 suits its detector's broad heatmaps; a sharper model
needs a smaller K, or the top-K statistics are dominated by background pixels and
the var/cov sets are wide and not adaptive. For each candidate K this prints, on
images of a validation split (not the training split, whose heatmaps are sharper than
on new images and favour a small K; never the calibration or test split, so that K is
fixed before calibration and the guarantee is untouched):

- the visible PCK@0.05 of the top-K mean (the service's var/cov point), and
- the median area of ICP-var and ICP-cov sets at eps = 0.1 (keypoint scope),
  calibrated on the even images and measured on the odd ones, in heatmap pixels^2
  (heatmaps are box-relative, so areas compare across object sizes),

and recommends the K with the smallest median ICP-cov area (cov is the service's default).
``--write`` stores it as ``heatmap.top_k`` in the model's manifest.json.
"""

from __future__ import annotations

import argparse
import math
from dataclasses import dataclass, fields
from pathlib import Path

import numpy as np

from service.conformal import conformal_threshold, nonconformity_scores, point_estimates, prediction_sets
from service.detector.crop import apply_affines, invert_affines
from service.detector.manifest import Manifest, load_manifest
from training.evaluate_detector import PCK_THRESHOLD, image_instances
from training.manifest import write_manifest

CANDIDATES = (4, 9, 16, 25, 36, 64, 100)
EPSILON = 0.1


@dataclass(frozen=True)
class KeypointRows:
    """One row per (instance, keypoint) of the sampled images."""

    heatmaps: np.ndarray  # (M, H, W) float32
    labels: np.ndarray  # (M, 2) heatmap coordinates
    visibility: np.ndarray  # (M,) COCO v
    column: np.ndarray  # (M,) output channel, the calibration column
    calibration: np.ndarray  # (M,) True on even images
    to_image: np.ndarray  # (M, 2, 3) heatmap -> image affine
    box_side: np.ndarray  # (M,) max(box w, h)


def collect_rows(data: Path, model_dir: Path, images: int) -> tuple[KeypointRows, int]:
    """Every labelled keypoint of the first ``images`` images, and how many images had instances."""
    manifest = load_manifest(model_dir)
    parts: dict[str, list[np.ndarray]] = {field.name: [] for field in fields(KeypointRows)}
    count = 0
    for i, found in enumerate(image_instances(data, model_dir, images, desc="select top-K")):
        count += 1
        n, k, h, w = found.heatmaps.shape
        parts["heatmaps"].append(found.heatmaps.reshape(n * k, h, w))
        parts["labels"].append(apply_affines(found.affines, found.labels[:, :, :2]).reshape(n * k, 2))
        parts["visibility"].append(found.labels[:, :, 2].ravel())
        parts["column"].append(np.array([manifest.object(o).keypoints for o in found.objects]).ravel())
        parts["calibration"].append(np.full(n * k, i % 2 == 0))
        parts["to_image"].append(np.repeat(invert_affines(found.affines), k, axis=0))
        parts["box_side"].append(np.repeat(np.maximum(found.boxes[:, 2], found.boxes[:, 3]), k))
    return KeypointRows(**{name: np.concatenate(values) for name, values in parts.items()}), count


def visible_pck(rows: KeypointRows, manifest: Manifest, top_k: int) -> float:
    test = ~rows.calibration & (rows.visibility == 2)
    spec = manifest.heatmap
    points = point_estimates("cov", rows.heatmaps[test], spec.normalization, top_k, spec.temperature)
    in_image = apply_affines(rows.to_image[test], points[:, None, :])[:, 0, :]
    labels = apply_affines(rows.to_image[test], rows.labels[test][:, None, :])[:, 0, :]
    errors = np.linalg.norm(in_image - labels, axis=1) / rows.box_side[test]
    return float(np.mean(errors <= PCK_THRESHOLD))


def median_set_area(
    rows: KeypointRows, manifest: Manifest, kind: str, top_k: int, epsilon: float = EPSILON
) -> float:
    """Median ICP set area (heatmap px^2) on the odd images, calibrated per column on the even ones."""
    spec = manifest.heatmap
    options = {"normalization": spec.normalization, "top_k": top_k, "temperature": spec.temperature}
    labeled = rows.visibility > 0
    calibration, test = rows.calibration & labeled, ~rows.calibration & labeled
    scores = nonconformity_scores(kind, rows.heatmaps[calibration], rows.labels[calibration], **options)
    thresholds = np.full(manifest.num_keypoints, math.inf)
    for column in np.unique(rows.column[calibration]):
        thresholds[column] = conformal_threshold(scores[rows.column[calibration] == column], epsilon)
    _, shapes = prediction_sets(kind, rows.heatmaps[test], thresholds[rows.column[test]], **options)
    with np.errstate(divide="ignore"):
        areas = math.pi / np.sqrt(np.linalg.det(shapes))
    return float(np.median(areas))


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--data", type=Path, required=True, help="a validation split (COCO folder)")
    parser.add_argument("--model", type=Path, required=True, help="model directory (onnx + manifest)")
    parser.add_argument("--images", type=int, default=400)
    parser.add_argument("--candidates", type=int, nargs="+", default=list(CANDIDATES))
    parser.add_argument("--epsilon", type=float, default=EPSILON, help="miscoverage of the compared sets")
    parser.add_argument("--write", action="store_true", help="store the recommended K in manifest.json")
    args = parser.parse_args(argv)
    manifest = load_manifest(args.model)
    rows, images = collect_rows(args.data, args.model, args.images)
    print(f"{len(rows.labels)} keypoints of {images} images of {args.data}; eps {args.epsilon}")
    print("| top_k | visible PCK@0.05 of the top-K mean | median ICP-var area | median ICP-cov area |")
    print("|---|---|---|---|")
    areas: dict[int, float] = {}
    for top_k in args.candidates:
        areas[top_k] = median_set_area(rows, manifest, "cov", top_k, args.epsilon)
        var_area = median_set_area(rows, manifest, "var", top_k, args.epsilon)
        print(f"| {top_k} | {visible_pck(rows, manifest, top_k):.3f} | {var_area:.1f} | {areas[top_k]:.1f} |")
    print(f"peak (no K): median ICP-peak area {median_set_area(rows, manifest, 'peak', 1, args.epsilon):.1f}")
    best = min(areas, key=areas.get)
    if not math.isfinite(areas[best]):
        raise SystemExit(
            "every candidate gives unbounded sets (too few calibration scores per keypoint for this "
            "epsilon): use more --images or a larger --epsilon; nothing written"
        )
    print(f"recommended top_k: {best} (smallest median ICP-cov area)")
    if args.write:
        heatmap = manifest.heatmap.model_copy(update={"top_k": best})
        print(f"wrote {write_manifest(args.model, manifest.model_copy(update={'heatmap': heatmap}))}")
        print(
            "calibrations scored under the old top_k are now refused: recalibrate, e.g. "
            f"keypoint-service calibrate <calibration split> --bundle {args.model}/default_calibration.npz"
        )


if __name__ == "__main__":
    main()
