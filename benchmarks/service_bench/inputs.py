"""The request the benchmark sends: one 640x480 JPEG of the samples folder with 1 or 4 boxes."""

from __future__ import annotations

import base64
import json
from dataclasses import dataclass
from pathlib import Path

import numpy as np

BOUNDARY = "----cks-bench-boundary"


@dataclass(frozen=True)
class Sample:
    """One image file and the instances sent with it."""

    name: str
    jpeg: bytes
    objects: tuple[str, ...]
    boxes: np.ndarray  # (N, 4) x, y, w, h

    @property
    def instances(self) -> list[dict]:
        return [
            {"object": obj, "bbox": [float(v) for v in box]}
            for obj, box in zip(self.objects, self.boxes, strict=True)
        ]

    def with_instances(self, count: int) -> Sample:
        """The first ``count`` instances (repeated if the image has fewer)."""
        index = np.arange(count) % len(self.objects)
        return Sample(self.name, self.jpeg, tuple(self.objects[i] for i in index), self.boxes[index])

    def parameters_json(self) -> str:
        return json.dumps({"instances": self.instances})

    def multipart_body(self) -> tuple[bytes, str]:
        """``(body, content type)`` of a multipart/form-data predict request."""
        head = (
            f'--{BOUNDARY}\r\nContent-Disposition: form-data; name="image"; filename="{self.name}"\r\n'
            "Content-Type: image/jpeg\r\n\r\n"
        ).encode()
        request = (
            f'\r\n--{BOUNDARY}\r\nContent-Disposition: form-data; name="request"\r\n'
            f"Content-Type: application/json\r\n\r\n{self.parameters_json()}\r\n--{BOUNDARY}--\r\n"
        ).encode()
        return head + self.jpeg + request, f"multipart/form-data; boundary={BOUNDARY}"

    def json_body(self) -> tuple[bytes, str]:
        """``(body, content type)`` of an application/json predict request (base64 image)."""
        body = {"instances": self.instances, "image_base64": base64.b64encode(self.jpeg).decode()}
        return json.dumps(body).encode(), "application/json"


def load_sample(samples_dir: Path) -> Sample:
    """The image of the COCO samples folder with the most annotated instances."""
    coco = json.loads((samples_dir / "annotations.json").read_text())
    categories = {c["id"]: c["name"] for c in coco["categories"]}
    by_image: dict[int, list[dict]] = {}
    for annotation in coco["annotations"]:
        by_image.setdefault(annotation["image_id"], []).append(annotation)
    image_id = max(by_image, key=lambda i: (len(by_image[i]), -i))
    image = next(i for i in coco["images"] if i["id"] == image_id)
    annotations = by_image[image_id]
    return Sample(
        name=image["file_name"].rsplit("/", 1)[-1],
        jpeg=(samples_dir / image["file_name"]).read_bytes(),
        objects=tuple(categories[a["category_id"]] for a in annotations),
        boxes=np.array([a["bbox"] for a in annotations], dtype=np.float64),
    )
