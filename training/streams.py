"""Camera sequences: one scene filmed by a camera moving smoothly, frame after frame.

A sequence composes one scene as ``training.scene.render_scene`` does (objects, clutter,
occluders, ground, light, background) and renders it from a camera that orbits the table a
little from frame to frame, so consecutive frames are as correlated as a real camera's. The
labels are the generator's (``training.annotate``). A ``Shift`` renders the sequences a
calibration on ordinary renders was not made for: heavier occlusion, blur, lower
resolution, a farther camera. Sequence ``s`` of a split is a pure function of ``(seed, s)``.
"""

from __future__ import annotations

from dataclasses import dataclass, replace

import cv2
import numpy as np

from training.scene import Rendered, World, compose_scene, render_view, sample_pose
from training.textures import texture

#: largest orbit speed (azimuth, degrees per frame) and elevation swing (degrees) of a sequence
MAX_ORBIT_DEG = 1.0
ELEVATION_SWING_DEG = 4.0


@dataclass(frozen=True)
class Shift:
    """How a sequence departs from the ordinary renders (the default departs in nothing)."""

    extra_occluders: int = 0  # distractors between the camera and the objects
    blur_sigma: float = 0.0  # Gaussian blur, pixels
    downscale: int = 1  # render, shrink by this factor, enlarge back: fewer pixels of detail
    distance: float = 1.0  # camera distance factor

    def degrade(self, rgb: np.ndarray) -> np.ndarray:
        if self.downscale > 1:
            height, width = rgb.shape[:2]
            small = (width // self.downscale, height // self.downscale)
            rgb = cv2.resize(cv2.resize(rgb, small, interpolation=cv2.INTER_AREA), (width, height))
        if self.blur_sigma > 0:
            rgb = cv2.GaussianBlur(rgb, (0, 0), self.blur_sigma)
        return rgb


#: the shifted sequences of the benchmarks and tests
SHIFTS = {
    "none": Shift(),
    "heavy_occlusion": Shift(extra_occluders=3),
    "blur": Shift(blur_sigma=2.5),
    "low_resolution": Shift(downscale=4),
    "farther": Shift(distance=1.6),
}


def render_sequence(
    world: World, rng: np.random.Generator, frames: int, shift: Shift = Shift(), moving: bool = True
) -> list[Rendered]:
    """``frames`` consecutive views of one scene; ``moving`` False keeps the camera still."""
    world.park_all()
    start = sample_pose(rng)
    start = replace(start, distance=start.distance * shift.distance)
    objects = compose_scene(world, rng, start.camera(world), shift.extra_occluders)
    light_seed = int(rng.integers(2**32))
    background = texture(rng, (world.height, world.width))
    orbit = np.deg2rad(rng.uniform(-MAX_ORBIT_DEG, MAX_ORBIT_DEG)) if moving else 0.0
    swing = np.deg2rad(ELEVATION_SWING_DEG) if moving else 0.0
    phase = rng.uniform(0, 2 * np.pi)
    views = []
    for frame in range(frames):
        pose = replace(
            start,
            azimuth=start.azimuth + orbit * frame,
            elevation=start.elevation + swing * (np.sin(phase + 0.05 * frame) - np.sin(phase)),
        )
        view = render_view(world, pose.camera(world), light_seed, background)
        view.rgb = shift.degrade(view.rgb)
        view.objects = objects
        views.append(view)
    return views
