"""Crop affines: the half-pixel convention holds in the image, the crop and the heatmap."""

from __future__ import annotations

import numpy as np
import pytest

from service.detector.crop import apply_affines, crop_affines, invert_affines, rescale_affines, warp_crop


def test_box_centre_maps_to_crop_centre_and_side_to_padded_size():
    boxes = np.array([[10.0, 20.0, 50.0, 30.0], [0.0, 0.0, 8.0, 16.0]])
    affines = crop_affines(boxes, padding=0.25, size=(128, 96))
    centres = boxes[:, :2] + boxes[:, 2:] / 2
    np.testing.assert_allclose(apply_affines(affines, centres), [[48, 64], [48, 64]])
    sides = np.maximum(boxes[:, 2], boxes[:, 3]) * 1.25
    np.testing.assert_allclose(affines[:, 0, 0], 96 / sides)
    np.testing.assert_allclose(affines[:, 1, 1], 128 / sides)


def test_warp_puts_a_pixel_where_the_affine_says():
    image = np.zeros((100, 120, 3), np.uint8)
    image[40, 60] = 255  # its centre is (60.5, 40.5)
    affine = crop_affines(np.array([[40.0, 20.0, 40.0, 40.0]]), padding=0.0, size=(40, 40))[0]
    crop = warp_crop(image, affine, (40, 40))
    row, col = np.argwhere(crop[:, :, 0] == 255)[0]
    mapped = apply_affines(affine[None], np.array([[60.5, 40.5]]))
    np.testing.assert_allclose(mapped, [[col + 0.5, row + 0.5]])


@pytest.mark.parametrize("scale", [0.5, 2.0, 3.7])
def test_scaled_warp_keeps_pixel_centres_aligned(scale):
    """A blob's intensity centroid moves exactly as the affine says, up- or downscaled."""
    yy, xx = np.mgrid[0:200, 0:200] + 0.5
    blob = np.exp(-((xx - 97.3) ** 2 + (yy - 103.9) ** 2) / (2 * 5.0**2))  # well inside every crop
    image = (blob * 255).astype(np.float32)
    side = 200 / scale
    affine = crop_affines(np.array([[100 - side / 2, 100 - side / 2, side, side]]), 0.0, (200, 200))[0]
    crop = warp_crop(image, affine, (200, 200)).astype(np.float64)
    cy, cx = (np.mgrid[0:200, 0:200] + 0.5).reshape(2, -1) @ crop.ravel() / crop.sum()
    expected = apply_affines(affine[None], np.array([[97.3, 103.9]]))[0]
    np.testing.assert_allclose([cx, cy], expected, atol=0.05)


def test_invert_and_rescale_compose():
    affines = crop_affines(np.array([[5.0, 7.0, 30.0, 44.0]]), 0.25, (128, 128))
    heatmap = rescale_affines(affines, (128, 128), (64, 64))
    points = np.array([[12.0, 30.0]])
    np.testing.assert_allclose(apply_affines(heatmap, points), apply_affines(affines, points) / 2)
    np.testing.assert_allclose(apply_affines(invert_affines(heatmap), apply_affines(heatmap, points)), points)


def test_preprocessing_matches_the_manifest_formula_for_colour_and_gray_images():
    from service.detector.manifest import InputSpec, Manifest
    from service.detector.preprocess import build_batch

    manifest = Manifest(
        name="m",
        input=InputSpec(name="image", height=8, width=8, mean=(0.1, 0.2, 0.3), std=(0.5, 0.6, 0.7)),
        crop={"padding": 0.0},
        output={"name": "heatmaps", "height": 4, "width": 4},
        keypoints=[{"index": 0, "name": "k", "object": "o"}],
        objects=[{"name": "o", "keypoints": [0]}],
    )
    rng = np.random.default_rng(1)
    image = rng.integers(0, 256, (20, 30, 3), dtype=np.uint8)
    box = np.array([[11.0, 6.0, 8.0, 8.0]])  # crop = pixels 11..18 x 6..13 exactly
    batch, _ = build_batch(image, box, manifest)
    rgb = image[6:14, 11:19, ::-1].astype(np.float32) / 255
    expected = ((rgb - np.float32([0.1, 0.2, 0.3])) / np.float32([0.5, 0.6, 0.7])).transpose(2, 0, 1)
    np.testing.assert_allclose(batch[0], expected, rtol=1e-6, atol=1e-6)
    gray, _ = build_batch(image[:, :, 1], box, manifest)
    np.testing.assert_allclose(gray[0, 0], gray[0, 2] * 0.7 / 0.5 + (0.3 - 0.1) / 0.5, rtol=1e-5, atol=1e-5)
