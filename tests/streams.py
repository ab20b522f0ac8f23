"""Camera sequences rendered in the test process, as a client would send them: per frame its JPEG
and its instances (object, box) from the generator's labels (training/streams.py)."""

from __future__ import annotations

from collections.abc import Iterable

import cv2
import numpy as np

from training.annotate import annotate_scene
from training.objects import OBJECT_CLASSES
from training.scene import World
from training.streams import SHIFTS, render_sequence

#: (JPEG bytes, instances) of one frame
RequestFrame = tuple[bytes, list[dict]]


def render_requests(seed: int, sequences: int, frames: int, shift: str = "none") -> list[list[RequestFrame]]:
    """``sequences`` scenes of ``frames`` frames each (sequence s drawn from ``(seed, s)``)."""
    return _render([[seed, s] for s in range(sequences)], frames, shift)


def render_scenes(seeds: Iterable[int], frames: int, shift: str = "none") -> list[list[RequestFrame]]:
    """A scene per seed, the one ``render_requests(seed, 1, frames, shift)`` renders; one world for
    all (loading a world's textures takes longer than rendering a frame)."""
    return _render([[seed, 0] for seed in seeds], frames, shift)


def _render(entropies: list[list[int]], frames: int, shift: str) -> list[list[RequestFrame]]:
    world = World()
    try:
        return [
            [
                _request(view)
                for view in render_sequence(world, np.random.default_rng(e), frames, SHIFTS[shift])
            ]
            for e in entropies
        ]
    finally:
        world.close()


def _request(view) -> RequestFrame:  # noqa: ANN001 - a training.scene.Rendered
    jpeg = cv2.imencode(".jpg", view.rgb[:, :, ::-1], [cv2.IMWRITE_JPEG_QUALITY, 90])[1].tobytes()
    instances = [
        {"object": OBJECT_CLASSES[a["category_id"] - 1].name, "bbox": a["bbox"]} for a in annotate_scene(view)
    ]
    return jpeg, instances
