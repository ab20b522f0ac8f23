"""Vectorized conformal scoring vs a per-heatmap loop of the same formulas.

Run: python -m benchmarks.bench_conformal   (or python benchmarks/bench_conformal.py)

Scores one batch of 76 heatmaps of 64x64 (the paper's LM-O setting) for each
nonconformity function, side by side in one run, and prints microseconds per
heatmap and the speed-up. The loop mirrors the authors' reference code: per
keypoint, anchor normalization, full argsort for the top-K, np.linalg.inv, on
the array it is given. Both get the same float32 batch, the detector's output
dtype (``--dtype float64`` for the other case). The vectorized scores are
checked against the loop run on the float64 copy of the same values (1e-9).
Timings are the best of 5 repeats; the load average is printed because the
machine may be shared (a loaded machine inflates both columns, ratios less).
"""

from __future__ import annotations

import argparse
import os
import sys
import timeit
from pathlib import Path

import numpy as np

if __package__ in (None, ""):
    sys.path.insert(0, str(Path(__file__).resolve().parents[1]))

from service.conformal import nonconformity_scores  # noqa: E402
from service.conformal.kernel import native_kernel_available  # noqa: E402

N_HEATMAPS, SIZE, TOP_K = 76, 64, 100


def make_batch(seed: int = 0) -> tuple[np.ndarray, np.ndarray]:
    rng = np.random.default_rng(seed)
    grid = np.arange(SIZE) + 0.5
    centers = rng.uniform(10, 54, (N_HEATMAPS, 2))
    sigmas = rng.uniform(1, 6, N_HEATMAPS)[:, None, None]
    squared = (grid[None, None, :] - centers[:, 0, None, None]) ** 2 + (
        grid[None, :, None] - centers[:, 1, None, None]
    ) ** 2
    heatmaps = np.exp(-squared / (2 * sigmas**2)) + 0.05 * rng.standard_normal((N_HEATMAPS, SIZE, SIZE))
    return heatmaps, centers + rng.normal(0, 2, centers.shape)


def loop_score(kind: str, heatmap: np.ndarray, keypoint: np.ndarray) -> float:
    heatmap = heatmap - np.min(heatmap)
    heatmap[heatmap < np.median(heatmap)] = 0
    heatmap = heatmap / np.sum(heatmap)
    if kind == "peak":
        row, col = np.unravel_index(np.argmax(heatmap.ravel()), heatmap.shape)
        return heatmap[row, col] * np.linalg.norm(keypoint - np.array([col + 0.5, row + 0.5]))
    rows, cols = np.unravel_index(np.flip(np.argsort(heatmap.ravel())), heatmap.shape)
    weights = heatmap[rows, cols][:TOP_K]
    weights = weights / weights.sum()
    points = np.stack([cols[:TOP_K] + 0.5, rows[:TOP_K] + 0.5], axis=1)
    mean = weights @ points
    diff = points - mean
    sigma = diff.T @ np.diag(weights) @ diff
    if kind == "var":
        return np.linalg.norm(keypoint - mean) / np.sqrt(max(np.trace(sigma), 1 / 6))
    offset = keypoint - mean
    return offset @ np.linalg.inv(sigma) @ offset


def per_heatmap_us(function, repeats: int) -> float:
    best = min(timeit.repeat(function, number=repeats, repeat=5))
    return best / repeats / N_HEATMAPS * 1e6


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    parser.add_argument("--dtype", choices=("float32", "float64"), default="float32")
    dtype = np.dtype(parser.parse_args().dtype)
    exact_heatmaps, keypoints = make_batch()
    heatmaps = exact_heatmaps.astype(dtype)
    values = heatmaps.astype(np.float64)
    print(f"batch: {N_HEATMAPS} heatmaps {SIZE}x{SIZE} {dtype}, top_k={TOP_K}, normalization=anchor")
    print("(timings on a possibly shared machine; load average printed per row)")
    print(f"{'kind':<6}{'loop us/hm':>12}{'vectorized us/hm':>18}{'speed-up':>10}{'load avg (1m)':>15}")
    for kind in ("peak", "var", "cov"):
        vectorized = nonconformity_scores(kind, heatmaps, keypoints, top_k=TOP_K)
        looped = [loop_score(kind, h, k) for h, k in zip(values, keypoints, strict=True)]
        np.testing.assert_allclose(vectorized, looped, rtol=1e-9)
        loop_us = per_heatmap_us(
            lambda kind=kind: [loop_score(kind, h, k) for h, k in zip(heatmaps, keypoints, strict=True)],
            3,
        )
        vector_us = per_heatmap_us(
            lambda kind=kind: nonconformity_scores(kind, heatmaps, keypoints, top_k=TOP_K), 20
        )
        load = os.getloadavg()[0]
        print(f"{kind:<6}{loop_us:>12.1f}{vector_us:>18.1f}{loop_us / vector_us:>9.1f}x{load:>15.2f}")
    kernel = "built" if native_kernel_available() else "MISSING (needs a C compiler at install): numpy path"
    print(f"native anchor-median kernel (service/conformal/kernel.py): {kernel}")


if __name__ == "__main__":
    main()
