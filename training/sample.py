"""Copy the first few images of a split (with their annotations) into a small demo sample.

python -m training.sample --data data/lmo_synth/test --out models/lmo-synth-unet/samples --images 12
"""

from __future__ import annotations

import argparse
import shutil
from pathlib import Path

from training.coco import ANNOTATIONS_FILENAME, read_coco, write_coco


def make_sample(data: Path, out: Path, images: int) -> Path:
    coco = read_coco(Path(data) / ANNOTATIONS_FILENAME)
    annotated = {a["image_id"] for a in coco["annotations"]}
    chosen = [im for im in coco["images"] if im["id"] in annotated][:images]
    ids = {im["id"] for im in chosen}
    (out / "images").mkdir(parents=True, exist_ok=True)
    for im in chosen:
        shutil.copyfile(Path(data) / im["file_name"], out / im["file_name"])
    anns = [a for a in coco["annotations"] if a["image_id"] in ids]
    source = coco.get("info", {})
    info = {**source, "description": f"sample of {source.get('description', data)}", "images": len(chosen)}
    path = out / ANNOTATIONS_FILENAME
    write_coco(path, chosen, anns, info)
    return path


def main(argv: list[str] | None = None) -> None:
    parser = argparse.ArgumentParser(description=__doc__)
    parser.add_argument("--data", type=Path, required=True)
    parser.add_argument("--out", type=Path, required=True)
    parser.add_argument("--images", type=int, default=12)
    args = parser.parse_args(argv)
    print(f"wrote {make_sample(args.data, args.out, args.images)}")


if __name__ == "__main__":
    main()
