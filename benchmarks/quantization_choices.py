"""Which int8 choices `keypoint-service optimize` makes, by measurement: weights with a scale per
output channel or per tensor, and whether the node reading the image and the node writing the
heatmaps stay float. Each choice is quantized from the same range images and scored on other images
of the folder: the distance from each keypoint's heatmap argmax to its label (image pixels) and the
model's run at batch 1 and 4 on one thread, interleaved in one process.

    python -m benchmarks.quantization_choices data/lmo_synth/calibration_2027 --images 300
"""

from __future__ import annotations

import argparse
import itertools
import tempfile
import time
from pathlib import Path

import numpy as np

from service.calibration.coco import CocoBatch, load_coco_batch
from service.calibration.variants import range_crops, split_for_ranges
from service.cli import DEFAULT_RANGE_IMAGES
from service.detector.compression import Int8Choices, quantize_int8
from service.detector.crop import apply_affines
from service.detector.images import decode_image
from service.detector.manifest import MODEL_FILENAME
from service.detector.preprocess import build_batch
from service.detector.session import CPU, Detector, create_session, instance_heatmaps
from service.infra.settings import DEFAULT_MODEL_DIR

MAX_PIXELS = 50_000_000


def argmax_errors(session, detector: Detector, batch: CocoBatch) -> np.ndarray:  # noqa: ANN001
    """Per labelled keypoint: image pixels from the heatmap's argmax pixel centre to the label."""
    manifest, errors = detector.manifest, []
    for image_id, instances in batch.instances_by_image().items():
        image = decode_image(batch.images[image_id].path.read_bytes(), MAX_PIXELS)
        boxes = np.stack([i.bbox for i in instances])
        inputs, affines = build_batch(image, boxes, manifest)
        heatmaps = session.run([manifest.output.name], {manifest.input.name: inputs})[0]
        rows = instance_heatmaps(manifest, heatmaps, [i.object_name for i in instances], affines)
        flat = rows.heatmaps.reshape(len(rows.heatmaps), -1).argmax(axis=1)
        peak = np.stack([flat % manifest.output.width, flat // manifest.output.width], axis=1) + 0.5
        labels = apply_affines(affines[rows.instance_index], np.concatenate([i.keypoints for i in instances]))
        per_pixel = (
            np.asarray([max(b[2], b[3]) for b in boxes]) * (1 + manifest.crop.padding) / manifest.output.width
        )
        errors.append(np.linalg.norm(peak - labels, axis=1) * per_pixel[rows.instance_index])
    values = np.concatenate(errors)
    return values[~np.isnan(values)]


def run_times(sessions: dict, inputs: np.ndarray, batch: int, rounds: int = 200) -> dict[str, float]:
    """Median ms of one run per session, the sessions taking turns."""
    times: dict[str, list[float]] = {name: [] for name in sessions}
    name_in = next(iter(sessions.values())).get_inputs()[0].name
    for start in itertools.islice(itertools.cycle(range(0, len(inputs) - batch, batch)), rounds):
        for name, session in sessions.items():
            began = time.perf_counter()
            session.run(None, {name_in: inputs[start : start + batch]})
            times[name].append(time.perf_counter() - began)
    return {name: 1000 * float(np.median(values)) for name, values in times.items()}


def main() -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("folder", type=Path, help="labelled renders no bundled split used")
    parser.add_argument("--model-dir", type=Path, default=DEFAULT_MODEL_DIR)
    parser.add_argument("--images", type=int, default=300, help="held-out images to score")
    args = parser.parse_args()
    detector = Detector(args.model_dir, 1)
    ranges, rest = split_for_ranges(load_coco_batch(args.folder, detector.manifest), DEFAULT_RANGE_IMAGES)
    kept = set(sorted(rest.instances_by_image())[: args.images])
    held_out = CocoBatch(
        rest.folder, rest.sha256, rest.images, tuple(i for i in rest.instances if i.image_id in kept)
    )
    crops = list(range_crops(ranges, detector, MAX_PIXELS))
    sessions = {"float32": create_session(args.model_dir / MODEL_FILENAME, 1, CPU, spinning=False)}
    with tempfile.TemporaryDirectory() as scratch:
        for per_channel, float_ends in itertools.product((True, False), (False, True)):
            name = f"{'per channel' if per_channel else 'per tensor'}{', ends float' if float_ends else ''}"
            target = Path(scratch) / f"{len(sessions)}.onnx"
            choices = Int8Choices(per_channel=per_channel, float_first_and_last=float_ends)
            quantize_int8(
                args.model_dir / MODEL_FILENAME, target, detector.manifest.input.name, iter(crops), choices
            )
            sessions[name] = create_session(target, 1, CPU, spinning=False)
        inputs = np.concatenate(crops)
        speed = {batch: run_times(sessions, inputs, batch) for batch in (1, 4)}
        kept_images = f"{len(held_out.instances)} instances of {len(kept)} images of {args.folder}"
        print(f"{kept_images}, ranges from {len(crops)} images\n")
        print(
            "| weights | median error (px) | 90th percentile (px) | run, batch 1 (ms) | run, batch 4 (ms) |"
        )
        print("|---|---|---|---|---|")
        for name, session in sessions.items():
            errors = argmax_errors(session, detector, held_out)
            cells = [
                f"{np.median(errors):.2f}",
                f"{np.percentile(errors, 90):.2f}",
                f"{speed[1][name]:.2f}",
                f"{speed[4][name]:.2f}",
            ]
            print(f"| {name} | {' | '.join(cells)} |")


if __name__ == "__main__":
    main()
