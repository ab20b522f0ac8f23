"""A model's faster variant: a complete model folder (a manifest naming the variant and its source,
the compressed model, and a calibration scored with it), made from a labelled batch. The crops of a
few of its images, cut as served, set the int8 ranges; the other images' instances calibrate, so the
calibration measures what the compression cost (docs/variants.md)."""

from __future__ import annotations

import json
from collections.abc import Iterator
from dataclasses import replace
from pathlib import Path

import numpy as np

from service.calibration.coco import CocoBatch
from service.detector.compression import convert_float16, quantize_int8
from service.detector.images import decode_image
from service.detector.manifest import MANIFEST_FILENAME, MODEL_FILENAME, VariantSpec
from service.detector.preprocess import build_batch
from service.detector.session import Detector, file_sha256
from service.errors import InvalidInput


def split_for_ranges(batch: CocoBatch, range_images: int) -> tuple[CocoBatch, CocoBatch]:
    """(the images that set the ranges, the rest), ``range_images`` spread evenly over the batch."""
    ids = sorted(batch.instances_by_image())
    if range_images < 1 or len(ids) <= range_images:
        raise InvalidInput(
            f"the batch has {len(ids)} images with instances; --range-images {range_images} must be at least"
            " 1 and leave the others to calibrate with"
        )
    chosen = set(np.asarray(ids)[np.linspace(0, len(ids) - 1, range_images).round().astype(int)].tolist())
    ranges = tuple(i for i in batch.instances if i.image_id in chosen)
    rest = tuple(i for i in batch.instances if i.image_id not in chosen)
    return replace(batch, instances=ranges, rejected=()), replace(batch, instances=rest)


def write_variant(
    source: Detector, source_dir: Path, out_dir: Path, precision: str, ranges: CocoBatch, max_pixels: int
) -> VariantSpec:
    """Write ``out_dir``: the source's manifest naming the variant, and the compressed model.onnx."""
    out_dir.mkdir(parents=True, exist_ok=True)
    model = out_dir / MODEL_FILENAME
    if precision == "int8":
        quantize_int8(
            source_dir / MODEL_FILENAME,
            model,
            source.manifest.input.name,
            range_crops(ranges, source, max_pixels),
        )
        images = len(ranges.instances_by_image())
        described = f"{images} images of {ranges.folder.name} (annotations.json sha256 {ranges.sha256[:12]})"
    else:
        convert_float16(source_dir / MODEL_FILENAME, model)
        described = ""
    variant = VariantSpec(
        name=precision,
        source_name=source.manifest.name,
        source_sha256=source.model_hash,
        model_sha256=file_sha256(model),
        ranges=described,
    )
    manifest = json.loads((source_dir / MANIFEST_FILENAME).read_text(encoding="utf-8"))
    manifest["variant"] = variant.model_dump()
    (out_dir / MANIFEST_FILENAME).write_text(json.dumps(manifest, indent=2) + "\n", encoding="utf-8")
    return variant


def range_crops(batch: CocoBatch, detector: Detector, max_pixels: int) -> Iterator[np.ndarray]:
    """Each image's crops, preprocessed exactly as a predict request's."""
    for image_id, instances in batch.instances_by_image().items():
        image = decode_image(batch.images[image_id].path.read_bytes(), max_pixels)
        boxes = np.stack([instance.bbox for instance in instances])
        yield build_batch(image, boxes, detector.manifest)[0]
