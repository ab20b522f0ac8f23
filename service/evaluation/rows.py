"""One inference pass over a labeled COCO folder (the detector once per image), keeping per (instance,
keypoint) row what the evaluation needs instead of the heatmaps: the three scores (``score_image``),
the heatmap statistics, the crop affine, the label and its COCO visibility flag."""

from __future__ import annotations

import json
from collections.abc import Callable
from dataclasses import dataclass

import numpy as np

from service.calibration.coco import ANNOTATIONS_FILENAME, CocoBatch, LabeledInstance
from service.calibration.scoring import NONCONFORMITY_KINDS, score_image
from service.conformal import HeatmapStatistics, heatmap_statistics
from service.detector.images import decode_image
from service.detector.manifest import HeatmapSpec
from service.detector.session import Detector, InstanceHeatmaps
from service.errors import InvalidInput, ServiceError


@dataclass(frozen=True)
class Rows:
    """Row-aligned arrays, one row per (instance, keypoint of its object), instance-major."""

    image_id: np.ndarray  # (R,)
    instance: np.ndarray  # (R,) index of the instance within the batch
    channel: np.ndarray  # (R,) manifest keypoint index
    visibility: np.ndarray  # (R,) COCO v: 0 unlabeled, 1 occluded, 2 visible
    visib_fract: np.ndarray  # (R,) fraction of the object visible, when the labels give it (else NaN)
    label: np.ndarray  # (R, 2) true keypoint, image pixels (NaN when unlabeled)
    box_side: np.ndarray  # (R,) max(w, h) of the instance box, image pixels
    affine: np.ndarray  # (R, 2, 3) image -> heatmap affine of the row's crop
    statistics: HeatmapStatistics  # heatmap coordinates, as heatmap_statistics returned them
    scores: dict[str, np.ndarray]  # kind -> (R,), NaN when unlabeled
    images: int

    @property
    def labeled(self) -> np.ndarray:
        return self.visibility > 0

    @property
    def instances(self) -> int:
        return int(self.instance.max()) + 1 if self.instance.size else 0


class _RecordingDetector:
    """Passes ``infer`` through to the detector and keeps the last result (no second run)."""

    def __init__(self, detector: Detector) -> None:
        self.manifest = detector.manifest
        self._detector = detector
        self.last: InstanceHeatmaps | None = None

    def infer(self, image: np.ndarray, boxes: np.ndarray, objects: list[str]) -> InstanceHeatmaps:
        self.last = self._detector.infer(image, boxes, objects)
        return self.last


def collect_rows(
    batch: CocoBatch,
    detector: Detector,
    max_image_pixels: int,
    progress: Callable[[int], None] = lambda count: None,
) -> Rows:
    """Run the detector once per image of a validated batch and collect every row; an image that
    does not decode by the predict rule is refused (skipping it would measure another batch)."""
    flags, recorder = _visibility_flags(batch), _RecordingDetector(detector)
    parts: list[dict[str, np.ndarray]] = []
    offset, groups = 0, batch.instances_by_image()
    for image_id, instances in groups.items():
        record = batch.images[image_id]
        try:
            image = decode_image(record.path.read_bytes(), max_image_pixels)
        except ServiceError as error:
            detail = f"image file {record.file_name!r} cannot be evaluated: {error.detail}"
            raise InvalidInput(detail) from None
        scores = [scored.scores for scored in score_image(recorder, image, instances)]
        assert recorder.last is not None
        shape = recorder.last.heatmaps.shape[-2:]
        parts.append(_image_rows(recorder.last, instances, scores, flags, detector.manifest.heatmap))
        parts[-1]["instance"] += offset
        offset += len(instances)
        progress(len(instances))
    merged = {name: np.concatenate([p[name] for p in parts]) for name in parts[0]}
    scores = {kind: merged.pop(f"score_{kind}") for kind in NONCONFORMITY_KINDS}
    statistics = HeatmapStatistics(shape, *(merged.pop(name) for name in _STATISTICS))
    return Rows(**merged, statistics=statistics, scores=scores, images=len(groups))


_STATISTICS = ("uninformative", "peak_location", "peak_probability", "mean", "covariance")


def _image_rows(
    result: InstanceHeatmaps,
    instances: list[LabeledInstance],
    scores: list[dict[str, np.ndarray]],
    flags: dict[int, tuple[np.ndarray, float]],
    spec: HeatmapSpec,
) -> dict[str, np.ndarray]:
    rows = result.instance_index
    statistics = heatmap_statistics(result.heatmaps, spec.normalization, spec.top_k, spec.temperature)
    part = {
        "image_id": np.array([instances[i].image_id for i in rows]),
        "instance": rows.astype(np.int64),
        "channel": result.channel.astype(np.int64),
        "visibility": np.concatenate([flags[inst.annotation_id][0] for inst in instances]),
        "visib_fract": np.array([flags[instances[i].annotation_id][1] for i in rows]),
        "label": np.concatenate([inst.keypoints for inst in instances]),
        "box_side": np.array([max(instances[i].bbox[2], instances[i].bbox[3]) for i in rows]),
        "affine": result.affines[rows],
    }
    part |= {name: getattr(statistics, name) for name in _STATISTICS}
    return part | {f"score_{kind}": np.concatenate([s[kind] for s in scores]) for kind in NONCONFORMITY_KINDS}


def _visibility_flags(batch: CocoBatch) -> dict[int, tuple[np.ndarray, float]]:
    """annotation id -> (COCO visibility flags (K,), visib_fract): load_coco_batch keeps only
    whether a keypoint is labeled; the file was validated by it, so it parses."""
    document = json.loads((batch.folder / ANNOTATIONS_FILENAME).read_bytes())
    return {
        a["id"]: (np.asarray(a["keypoints"], dtype=np.int64)[2::3], float(a.get("visib_fract", np.nan)))
        for a in document["annotations"]
    }
