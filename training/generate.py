"""Generate one split of the synthetic LM-O-like benchmark as COCO keypoints.

    python -m training.generate --split test --out data/lmo_synth/test --images 1000 --seed 3
    python -m training.generate --split heldout --out data/lmo_synth/heldout_heavy --images 1500 \
        --seed 11 --occluders 3        # heavier occlusion: 3 more occluders per scene


Image ``i`` of a split is a pure function of ``(seed, i)``, so a split is reproducible
and can be rendered by several worker processes.
"""

from __future__ import annotations

import argparse
import multiprocessing as mp
from pathlib import Path

import cv2
import numpy as np
from tqdm import tqdm

from training.annotate import annotate_scene
from training.coco import ANNOTATIONS_FILENAME, write_coco
from training.scene import World, render_scene

JPEG_QUALITY = 90
_WORLD: World | None = None
_EXTRA_OCCLUDERS = 0


def _init_worker(width: int, height: int, extra_occluders: int = 0) -> None:
    global _WORLD, _EXTRA_OCCLUDERS
    _WORLD = World(width, height)
    _EXTRA_OCCLUDERS = extra_occluders


def render_one(args: tuple[int, int, Path]) -> tuple[int, list[dict], tuple[int, int]]:
    """Render image ``index`` of a split, write its JPEG, return its annotations (no ids)."""
    seed, index, out = args
    assert _WORLD is not None
    rendered = render_scene(_WORLD, np.random.default_rng([seed, index]), _EXTRA_OCCLUDERS)
    path = out / "images" / f"{index:06d}.jpg"
    cv2.imwrite(str(path), rendered.rgb[:, :, ::-1], [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY])
    return index, annotate_scene(rendered), (rendered.camera.width, rendered.camera.height)


def _assemble(results: list[tuple[int, list[dict], tuple[int, int]]]) -> tuple[list[dict], list[dict]]:
    images, annotations = [], []
    for index, anns, (width, height) in sorted(results, key=lambda r: r[0]):
        image_id = index + 1
        name = f"images/{index:06d}.jpg"
        images.append({"id": image_id, "file_name": name, "width": width, "height": height})
        for ann in anns:
            annotations.append({"id": len(annotations) + 1, "image_id": image_id, **ann})
    return images, annotations


def generate(
    out: Path,
    images: int,
    seed: int,
    split: str,
    width: int = 640,
    height: int = 480,
    workers: int = 1,
    progress: bool = True,
    extra_occluders: int = 0,
) -> Path:
    """Render ``images`` scenes into ``out`` and write ``out/annotations.json``.

    ``extra_occluders`` > 0 renders heavier occlusion (recorded in the annotations' info);
    0 keeps every image bit for bit as before the option existed.
    """
    out = Path(out)
    (out / "images").mkdir(parents=True, exist_ok=True)
    jobs = [(seed, i, out) for i in range(images)]
    bar = tqdm(total=images, desc=f"render {split}", disable=not progress, mininterval=5)
    results = []
    if workers <= 1:
        _init_worker(width, height, extra_occluders)
        for job in jobs:
            results.append(render_one(job))
            bar.update()
    else:
        with mp.get_context("spawn").Pool(workers, _init_worker, (width, height, extra_occluders)) as pool:
            for result in pool.imap_unordered(render_one, jobs, chunksize=8):
                results.append(result)
                bar.update()
    bar.close()
    imgs, anns = _assemble(results)
    info = {
        "description": f"lmo_synth {split}",
        "split": split,
        "seed": seed,
        "images": images,
        "generator": "training.generate (pybullet TinyRenderer)",
    }
    if extra_occluders:
        info["extra_occluders"] = extra_occluders
    path = out / ANNOTATIONS_FILENAME
    write_coco(path, imgs, anns, info)
    return path


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--split", required=True, help="split name recorded in the annotations (train, ...)")
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--images", type=int, required=True)
    parser.add_argument("--seed", type=int, required=True)
    parser.add_argument("--width", type=int, default=640)
    parser.add_argument("--height", type=int, default=480)
    parser.add_argument("--workers", type=int, default=1)
    parser.add_argument(
        "--occluders",
        type=int,
        default=0,
        help="extra occluders per scene, between the camera and the objects (default 0)",
    )
    args = parser.parse_args(argv)
    if args.occluders < 0:
        parser.error("--occluders must be >= 0")
    path = generate(
        args.out,
        args.images,
        args.seed,
        args.split,
        args.width,
        args.height,
        args.workers,
        extra_occluders=args.occluders,
    )
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
