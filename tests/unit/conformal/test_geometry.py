import math

import numpy as np
import pytest

from service.conformal import (
    ball_radii,
    ball_shapes,
    contains,
    ellipse_axes,
    map_sets_to_image,
    prediction_sets,
)

from .synthetic import gaussian_blobs


def _random_affine(rng, similarity: bool) -> np.ndarray:
    if similarity:
        angle, scale = rng.uniform(0, 2 * np.pi), rng.uniform(0.1, 3)
        linear = scale * np.array([[np.cos(angle), -np.sin(angle)], [np.sin(angle), np.cos(angle)]])
    else:
        linear = rng.normal(0, 1, (2, 2)) + 2 * np.eye(2)
    return np.hstack([linear, rng.normal(0, 20, (2, 1))])


@pytest.mark.parametrize("similarity", [True, False])
@pytest.mark.parametrize("kind", ["peak", "var", "cov"])
def test_points_inside_map_to_points_inside(kind, similarity):
    rng = np.random.default_rng(42)
    heatmaps, _ = gaussian_blobs(rng, 50, size=32, noise=0.01)
    centers, shapes = prediction_sets(kind, heatmaps, 1.5 if kind != "peak" else 0.05)
    affine = _random_affine(rng, similarity)
    image_centers, image_shapes = map_sets_to_image(centers, shapes, affine)
    linear, offset = affine[:, :2], affine[:, 2]
    for _ in range(20):
        heatmap_points = centers + rng.normal(0, 3, centers.shape)
        image_points = np.linalg.solve(linear, (heatmap_points - offset).T).T
        inside_heatmap = contains(heatmap_points, centers, shapes)
        np.testing.assert_array_equal(contains(image_points, image_centers, image_shapes), inside_heatmap)
    np.testing.assert_allclose(linear @ image_centers.T + offset[:, None], centers.T)


def test_ball_stays_ball_under_similarity():
    rng = np.random.default_rng(1)
    affine = _random_affine(rng, similarity=True)
    scale = math.sqrt(abs(np.linalg.det(affine[:, :2])))
    radii = rng.uniform(0.5, 5, 10)
    _, image_shapes = map_sets_to_image(rng.random((10, 2)), ball_shapes(radii), affine)
    np.testing.assert_allclose(image_shapes[:, 0, 1], 0, atol=1e-12)
    np.testing.assert_allclose(image_shapes[:, 0, 0], image_shapes[:, 1, 1])
    np.testing.assert_allclose(ball_radii(image_shapes), radii / scale)


def test_ellipse_axes_match_eigen_decomposition():
    rng = np.random.default_rng(2)
    factors = rng.normal(0, 1, (30, 2, 2))
    shapes = factors @ factors.transpose(0, 2, 1) + 0.1 * np.eye(2)
    semi_minor, semi_major, angles = ellipse_axes(shapes)
    eigenvalues, eigenvectors = np.linalg.eigh(shapes)
    np.testing.assert_allclose(semi_minor, 1 / np.sqrt(eigenvalues[:, 1]))
    np.testing.assert_allclose(semi_major, 1 / np.sqrt(eigenvalues[:, 0]))
    radians = np.radians(angles)
    direction = np.stack([np.cos(radians), np.sin(radians)], axis=1)
    alignment = np.abs(np.einsum("ni,ni->n", direction, eigenvectors[:, :, 0]))
    np.testing.assert_allclose(alignment, 1.0)
    assert np.all((angles > -90) & (angles <= 90))


def test_unbounded_and_point_sets():
    centers = np.zeros((2, 2))
    shapes = np.stack([np.zeros((2, 2)), np.diag([np.inf, np.inf])])
    assert contains(np.array([[1e9, 1e9], [0.0, 0.0]]), centers, shapes).tolist() == [True, True]
    assert contains(np.array([[0.0, 0.0], [0.0, 1e-9]]), centers, shapes).tolist() == [True, False]
    semi_minor, semi_major, _ = ellipse_axes(shapes)
    assert semi_minor.tolist() == [math.inf, 0.0] and semi_major.tolist() == [math.inf, 0.0]
    affine = _random_affine(np.random.default_rng(3), similarity=False)
    _, image_shapes = map_sets_to_image(centers, shapes, affine)
    assert np.all(image_shapes[0] == 0) and np.all(np.isinf(np.diag(image_shapes[1])))


def test_singular_affine_is_refused():
    with pytest.raises(ValueError):
        map_sets_to_image(np.zeros((1, 2)), np.eye(2)[None], np.zeros((2, 3)))
