"""Generate one split of the synthetic LM-O-like benchmark as COCO keypoints.

    python -m training.generate --split test --out data/lmo_synth/test --images 1000 --seed 3
    python -m training.generate --split heldout --out data/lmo_synth/heldout_heavy --images 1500 \
        --seed 11 --occluders 3        # heavier occlusion: 3 more occluders per scene
    python -m training.generate --split stream --out data/streams/heavy --sequences 20 --frames 30 \
        --seed 41 --occluders 3        # camera sequences (training/streams.py): 20 scenes x 30 frames


Image ``i`` of a split (sequence ``i`` with ``--sequences``) is a pure function of ``(seed, i)``,
so a split is reproducible and can be rendered by several worker processes. A sequence's frames
are named ``images/SSSSSS_FFFF.jpg`` and their COCO images carry ``sequence`` and ``frame``.
"""

from __future__ import annotations

import argparse
import multiprocessing as mp
from dataclasses import asdict, replace
from pathlib import Path

import cv2
import numpy as np
from tqdm import tqdm

from training.annotate import annotate_scene
from training.coco import ANNOTATIONS_FILENAME, write_coco
from training.scene import Rendered, World, render_scene
from training.streams import Shift, render_sequence

JPEG_QUALITY = 90
_WORLD: World | None = None
_SHIFT = Shift()
_FRAMES = 0  # frames per sequence; 0: single images

#: a written frame: its COCO image (no id) and its annotations (no ids)
Written = tuple[dict, list[dict]]


def _init_worker(width: int, height: int, shift: Shift | None = None, frames: int = 0) -> None:
    global _WORLD, _SHIFT, _FRAMES
    _WORLD = World(width, height)
    _SHIFT, _FRAMES = shift or Shift(), frames


def render_one(args: tuple[int, int, Path]) -> tuple[int, list[Written]]:
    """Render image (or sequence) ``index`` of a split, write its JPEGs, return its annotations."""
    seed, index, out = args
    assert _WORLD is not None
    rng = np.random.default_rng([seed, index])
    if not _FRAMES:
        return index, [_write(render_scene(_WORLD, rng, _SHIFT.extra_occluders), out, f"{index:06d}", {})]
    views = render_sequence(_WORLD, rng, _FRAMES, _SHIFT)
    return index, [
        _write(view, out, f"{index:06d}_{frame:04d}", {"sequence": index, "frame": frame})
        for frame, view in enumerate(views)
    ]


def _write(rendered: Rendered, out: Path, stem: str, extra: dict) -> Written:
    name = f"images/{stem}.jpg"
    cv2.imwrite(str(out / name), rendered.rgb[:, :, ::-1], [cv2.IMWRITE_JPEG_QUALITY, JPEG_QUALITY])
    image = {"file_name": name, "width": rendered.camera.width, "height": rendered.camera.height, **extra}
    return image, annotate_scene(rendered)


def _assemble(results: list[tuple[int, list[Written]]]) -> tuple[list[dict], list[dict]]:
    images, annotations = [], []
    for _, rendered in sorted(results, key=lambda r: r[0]):
        for image, anns in rendered:
            image_id = len(images) + 1
            images.append({"id": image_id, **image})
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
    frames: int = 0,
    shift: Shift | None = None,
) -> Path:
    """Render ``images`` scenes (sequences of ``frames`` frames when > 0) into ``out`` and write
    ``out/annotations.json``.

    ``extra_occluders`` > 0 renders heavier occlusion (recorded in the annotations' info);
    0 keeps every image bit for bit as before the option existed. ``shift`` (sequences only)
    adds blur, lower resolution or a farther camera; its occluders are ``extra_occluders``.
    """
    shift = replace(shift or Shift(), extra_occluders=extra_occluders)
    if shift != Shift(extra_occluders=extra_occluders) and not frames:
        raise ValueError("blur, downscale and distance shifts are rendered for sequences (frames > 0)")
    out = Path(out)
    (out / "images").mkdir(parents=True, exist_ok=True)
    jobs = [(seed, i, out) for i in range(images)]
    bar = tqdm(total=images, desc=f"render {split}", disable=not progress, mininterval=5)
    results = []
    if workers <= 1:
        _init_worker(width, height, shift, frames)
        for job in jobs:
            results.append(render_one(job))
            bar.update()
    else:
        with mp.get_context("spawn").Pool(workers, _init_worker, (width, height, shift, frames)) as pool:
            for result in pool.imap_unordered(render_one, jobs, chunksize=8):
                results.append(result)
                bar.update()
    bar.close()
    imgs, anns = _assemble(results)
    info = {
        "description": f"lmo_synth {split}",
        "split": split,
        "seed": seed,
        "images": len(imgs),
        "generator": "training.generate (pybullet TinyRenderer)",
    }
    if extra_occluders:
        info["extra_occluders"] = extra_occluders
    if frames:
        info |= {"sequences": images, "frames": frames, "shift": asdict(shift)}
    path = out / ANNOTATIONS_FILENAME
    write_coco(path, imgs, anns, info)
    return path


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(
        description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter
    )
    parser.add_argument("--split", required=True, help="split name recorded in the annotations (train, ...)")
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--images", type=int)
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
    parser.add_argument("--sequences", type=int, help="render this many camera sequences instead of --images")
    parser.add_argument("--frames", type=int, default=30, help="frames per sequence (default 30)")
    parser.add_argument("--blur", type=float, default=0.0, help="sequences: Gaussian blur sigma, pixels")
    parser.add_argument("--downscale", type=int, default=1, help="sequences: lose resolution by this factor")
    parser.add_argument("--distance", type=float, default=1.0, help="sequences: camera distance factor")
    args = parser.parse_args(argv)
    if args.occluders < 0:
        parser.error("--occluders must be >= 0")
    if (args.images is None) == (args.sequences is None):
        parser.error("give either --images or --sequences")
    if args.sequences is None and (args.blur, args.downscale, args.distance) != (0.0, 1, 1.0):
        parser.error("--blur, --downscale and --distance apply to --sequences")
    path = generate(
        args.out,
        args.images if args.sequences is None else args.sequences,
        args.seed,
        args.split,
        args.width,
        args.height,
        args.workers,
        extra_occluders=args.occluders,
        frames=0 if args.sequences is None else args.frames,
        shift=Shift(blur_sigma=args.blur, downscale=args.downscale, distance=args.distance),
    )
    print(f"wrote {path}")


if __name__ == "__main__":
    main()
