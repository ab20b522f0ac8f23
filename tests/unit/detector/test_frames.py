"""Image sources: crops from regions equal the whole frame's, bit for bit, for any box whose crop
context the region holds (the service's byte-identical answers rest on this), and the canvas
regions are placed on is all zeros again after each use."""

from __future__ import annotations

import numpy as np
import pytest

from service.detector import frames
from service.detector.crop import crop_affines, crop_contexts
from service.detector.frames import ImageSource, Region

SIZE = (128, 128)


@pytest.mark.parametrize(("width", "height", "channels"), [(640, 480, 3), (1920, 1080, 3), (1280, 720, 1)])
def test_crops_from_regions_are_the_whole_frames(width: int, height: int, channels: int) -> None:
    rng = np.random.default_rng(width + channels)
    shape = (height, width) if channels == 1 else (height, width, channels)
    frame = rng.integers(0, 256, shape, dtype=np.uint8)
    sides = rng.uniform(2, 400, (300, 2))
    corners = rng.uniform(-1, 1, (300, 2)) + rng.uniform(0, 1, (300, 2)) * ([width, height] - sides)
    boxes = np.concatenate([corners, sides], axis=1)
    affines = crop_affines(boxes, 0.25, SIZE)
    contexts = crop_contexts(boxes, 0.25, width, height)
    regions = tuple(
        Region(int(x0), int(y0), np.ascontiguousarray(frame[y0:y1, x0:x1]), instances=(i,))
        for i, (x0, y0, x1, y1) in enumerate(contexts)
    )
    from_regions = ImageSource(width, height, regions).crops(affines, SIZE)
    assert np.array_equal(from_regions, ImageSource.whole(frame).crops(affines, SIZE))
    assert not frames._canvases.canvas.any()


def test_rgb_regions_are_reordered_in_the_crops() -> None:
    rng = np.random.default_rng(1)
    bgr = rng.integers(0, 256, (480, 640, 3), dtype=np.uint8)
    rgb = np.ascontiguousarray(bgr[..., ::-1])
    affines = crop_affines(np.array([[100.0, 80.0, 60.0, 90.0], [0.0, 0.0, 640.0, 480.0]]), 0.25, SIZE)
    expected = ImageSource.whole(bgr).crops(affines, SIZE)
    assert np.array_equal(ImageSource.whole(rgb, rgb=True).crops(affines, SIZE), expected)
    assert np.array_equal(ImageSource.whole(rgb, rgb=True).pixels, bgr)
    with pytest.raises(ValueError, match="regions"):
        _ = ImageSource(640, 480, (Region(1, 1, bgr[1:, 1:]),)).pixels
