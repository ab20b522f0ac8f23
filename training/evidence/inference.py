"""One inference pass over a COCO split, cached: per (instance, keypoint) row, everything
the report needs (scores of the three functions and the baseline, heatmap statistics,
crop affine, labels, visibility), so no heatmap has to be kept.

The detector runs once per image (all boxes in one batch). Scores come from the service's
``score_image``; the same detector output is reused for the heatmap statistics (the
service's ``heatmap_statistics`` with the manifest's settings) and the baseline's mass
curves. Cached as ``<cache>/<split>-<key>.npz``, the key hashing the model, the
annotations and the baseline thresholds, so a rerun on the same inputs skips inference.
"""

from __future__ import annotations

import hashlib
import json
from dataclasses import dataclass, fields
from pathlib import Path

import numpy as np
from tqdm import tqdm

from service.calibration.coco import ANNOTATIONS_FILENAME, load_coco_batch
from service.calibration.scoring import NONCONFORMITY_KINDS, score_image
from service.conformal import HeatmapStatistics, heatmap_statistics, normalize_heatmaps
from service.detector.crop import apply_affines
from service.detector.runtime import Detector, InstanceHeatmaps
from service.image_decoding import decode_image
from training.evidence.baseline import BASELINE_KIND, label_pixels, mass_curves

CACHE_VERSION = "1"
MAX_IMAGE_PIXELS = 40_000_000
ALL_KINDS = (*NONCONFORMITY_KINDS, BASELINE_KIND)


@dataclass(frozen=True)
class SplitData:
    """Row-aligned arrays, one row per (instance, keypoint of its object), instance-major."""

    image_id: np.ndarray  # (R,)
    annotation_id: np.ndarray  # (R,)
    instance: np.ndarray  # (R,) index of the instance within the split
    channel: np.ndarray  # (R,) manifest keypoint index
    visibility: np.ndarray  # (R,) COCO v: 0 unlabeled, 1 occluded, 2 visible
    visib_fract: np.ndarray  # (R,) fraction of the object visible (per instance)
    label: np.ndarray  # (R, 2) true keypoint, image pixels (NaN when unlabeled)
    box_side: np.ndarray  # (R,) max(w, h) of the instance box, image pixels
    affine: np.ndarray  # (R, 2, 3) image -> heatmap affine of the row's crop
    uninformative: np.ndarray  # (R,) HeatmapStatistics fields, heatmap coordinates
    peak_location: np.ndarray
    peak_probability: np.ndarray
    mean: np.ndarray
    covariance: np.ndarray
    scores: dict[str, np.ndarray]  # kind -> (R,), NaN when unlabeled
    baseline_pixels: dict[float, np.ndarray]  # epsilon -> (R,) pixel count of the baseline set
    heatmap_shape: tuple[int, int]
    images: int

    @property
    def labeled(self) -> np.ndarray:
        return self.visibility > 0

    def statistics(self) -> HeatmapStatistics:
        """The rows' statistics, as ``heatmap_statistics`` returned them."""
        return HeatmapStatistics(
            self.heatmap_shape,
            self.uninformative,
            self.peak_location,
            self.peak_probability,
            self.mean,
            self.covariance,
        )

    def rows(self, mask: np.ndarray) -> SplitData:
        """The subset of rows ``mask`` (bool or indices)."""
        values = {f.name: getattr(self, f.name) for f in fields(self)}
        for name, value in values.items():
            if isinstance(value, np.ndarray):
                values[name] = value[mask]
        values["scores"] = {k: v[mask] for k, v in self.scores.items()}
        values["baseline_pixels"] = {k: v[mask] for k, v in self.baseline_pixels.items()}
        return SplitData(**values)


class _RecordingDetector:
    """Passes ``infer`` through to the detector and keeps the last result (no second run)."""

    def __init__(self, detector: Detector) -> None:
        self.manifest = detector.manifest
        self._detector = detector
        self.last: InstanceHeatmaps | None = None

    def infer(self, image: np.ndarray, boxes: np.ndarray, objects: list[str]) -> InstanceHeatmaps:
        self.last = self._detector.infer(image, boxes, objects)
        return self.last


def load_split(
    folder: Path,
    detector: Detector,
    cache_dir: Path,
    baseline_thresholds: dict[float, np.ndarray] | None = None,
) -> SplitData:
    """The split's rows, from the cache when the model, annotations and thresholds match."""
    folder = Path(folder)
    thresholds = baseline_thresholds or {}
    key = _cache_key(folder, detector, thresholds)
    path = Path(cache_dir) / f"{folder.name}-{key}.npz"
    if path.is_file():
        return _read_cache(path)
    data = collect_split(folder, detector, thresholds)
    path.parent.mkdir(parents=True, exist_ok=True)
    _write_cache(path, data)
    return data


def collect_split(
    folder: Path, detector: Detector, baseline_thresholds: dict[float, np.ndarray]
) -> SplitData:
    """Run the detector once per image of a COCO split and collect every row."""
    manifest = detector.manifest
    batch = load_coco_batch(folder, manifest)
    extra = _annotation_extras(folder)
    recorder = _RecordingDetector(detector)
    parts: list[dict[str, np.ndarray]] = []
    groups = batch.instances_by_image()
    instance_offset = 0
    for image_id, instances in tqdm(groups.items(), desc=f"infer {folder.name}", mininterval=5):
        image = decode_image(batch.images[image_id].path.read_bytes(), MAX_IMAGE_PIXELS)
        scores = [scored.scores for scored in score_image(recorder, image, instances)]
        assert recorder.last is not None
        part = _image_rows(recorder.last, instances, scores, extra, manifest.heatmap, baseline_thresholds)
        part["instance"] = part["instance"] + instance_offset
        instance_offset += len(instances)
        parts.append(part)
    return _assemble(parts, (manifest.output.height, manifest.output.width), len(groups))


def _image_rows(result, instances, scores, extra, spec, baseline_thresholds) -> dict[str, np.ndarray]:
    rows = result.instance_index
    labels = np.concatenate([inst.keypoints for inst in instances])
    affines = result.affines[rows]
    stats = heatmap_statistics(result.heatmaps, spec.normalization, spec.top_k, spec.temperature)
    probabilities = normalize_heatmaps(result.heatmaps, spec.normalization, spec.temperature)
    curves = mass_curves(probabilities)
    height, width = result.heatmaps.shape[1:]
    label_px = label_pixels(apply_affines(affines, labels), height, width)
    visibility = np.concatenate([extra[inst.annotation_id][0] for inst in instances])
    part = {
        "image_id": np.array([instances[i].image_id for i in rows]),
        "annotation_id": np.array([instances[i].annotation_id for i in rows]),
        "instance": rows.astype(np.int64),
        "channel": result.channel.astype(np.int64),
        "visibility": visibility,
        "visib_fract": np.array([extra[instances[i].annotation_id][1] for i in rows]),
        "label": labels,
        "box_side": np.array([max(instances[i].bbox[2], instances[i].bbox[3]) for i in rows]),
        "affine": affines,
        "uninformative": stats.uninformative,
        "peak_location": stats.peak_location,
        "peak_probability": stats.peak_probability,
        "mean": stats.mean,
        "covariance": stats.covariance,
    }
    for kind in NONCONFORMITY_KINDS:
        part[f"score_{kind}"] = np.concatenate([s[kind] for s in scores])
    mass = curves.label_scores(label_px)
    part[f"score_{BASELINE_KIND}"] = np.where(visibility > 0, mass, np.nan)
    for epsilon, thresholds in baseline_thresholds.items():
        part[f"baseline_{epsilon!r}"] = curves.areas(thresholds[result.channel])
    return part


def _annotation_extras(folder: Path) -> dict[int, tuple[np.ndarray, float]]:
    """annotation id -> (COCO visibility flags (K,), visib_fract); load_coco_batch drops both."""
    document = json.loads((folder / ANNOTATIONS_FILENAME).read_text())
    return {
        a["id"]: (np.asarray(a["keypoints"], dtype=np.int64)[2::3], float(a.get("visib_fract", np.nan)))
        for a in document["annotations"]
    }


def _assemble(parts: list[dict[str, np.ndarray]], heatmap_shape: tuple[int, int], images: int) -> SplitData:
    merged = {name: np.concatenate([p[name] for p in parts]) for name in parts[0]}
    return _from_arrays(merged, heatmap_shape, images)


def _from_arrays(arrays: dict[str, np.ndarray], heatmap_shape: tuple[int, int], images: int) -> SplitData:
    scores = {k.removeprefix("score_"): v for k, v in arrays.items() if k.startswith("score_")}
    baseline = {float(k.removeprefix("baseline_")): v for k, v in arrays.items() if k.startswith("baseline_")}
    plain = {k: v for k, v in arrays.items() if not k.startswith(("score_", "baseline_", "meta_"))}
    return SplitData(
        **plain, scores=scores, baseline_pixels=baseline, heatmap_shape=heatmap_shape, images=images
    )


def _write_cache(path: Path, data: SplitData) -> None:
    arrays = {
        f.name: getattr(data, f.name) for f in fields(data) if isinstance(getattr(data, f.name), np.ndarray)
    }
    arrays |= {f"score_{k}": v for k, v in data.scores.items()}
    arrays |= {f"baseline_{k!r}": v for k, v in data.baseline_pixels.items()}
    arrays |= {"meta_heatmap_shape": np.asarray(data.heatmap_shape), "meta_images": np.asarray(data.images)}
    temporary = path.with_suffix(".tmp.npz")
    np.savez(temporary, **arrays)
    temporary.replace(path)


def _read_cache(path: Path) -> SplitData:
    with np.load(path) as archive:
        arrays = {name: archive[name] for name in archive.files}
    shape = tuple(int(v) for v in arrays["meta_heatmap_shape"])
    return _from_arrays(arrays, (shape[0], shape[1]), int(arrays["meta_images"]))


def _cache_key(folder: Path, detector: Detector, thresholds: dict[float, np.ndarray]) -> str:
    digest = hashlib.sha256(CACHE_VERSION.encode())
    digest.update(detector.model_hash.encode())
    digest.update(detector.manifest.model_dump_json().encode())
    digest.update((folder / ANNOTATIONS_FILENAME).read_bytes())
    for epsilon in sorted(thresholds):
        digest.update(repr(epsilon).encode() + np.asarray(thresholds[epsilon], dtype=np.float64).tobytes())
    return digest.hexdigest()[:16]


def concatenate(first: SplitData, second: SplitData) -> SplitData:
    """Rows of both splits; instance and image ids of ``second`` are shifted to stay unique.

    Baseline pixel counts depend on thresholds and are dropped.
    """
    shift = {"instance": int(first.instance.max()) + 1, "image_id": int(first.image_id.max()) + 1}
    values = {}
    for f in fields(first):
        a, b = getattr(first, f.name), getattr(second, f.name)
        if isinstance(a, np.ndarray):
            values[f.name] = np.concatenate([a, b + shift.get(f.name, 0)])
    values["scores"] = {k: np.concatenate([first.scores[k], second.scores[k]]) for k in first.scores}
    return SplitData(
        **values, baseline_pixels={}, heatmap_shape=first.heatmap_shape, images=first.images + second.images
    )
