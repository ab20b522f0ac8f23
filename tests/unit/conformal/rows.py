"""Heatmap-like rows of every awkward kind, for the tests of the selection and the kernel."""

import numpy as np


def row_cases(rng: np.random.Generator) -> dict[str, np.ndarray]:
    """Name -> (rows, width): noise, ties, zeros, odd and tiny widths, extreme and mixed scales,
    heavy tails, a maximum shared by half the row, negatives, infinities, an int8 model's peaks."""
    noise = rng.normal(size=(30, 4096))
    distance = np.hypot(*np.mgrid[-32:32, -32:32]).ravel() + rng.uniform(0, 8, (30, 1))
    return {
        "gaussian noise": noise,
        "few distinct values (ties)": np.round(noise * 2),
        "mostly exact zeros": np.where(rng.random((30, 4096)) < 0.7, 0.0, rng.random((30, 4096))),
        "odd width": noise[:, :4095],
        "width 2": noise[:, :2],
        "width 3": noise[:, :3],
        "constant": np.full((4, 100), 3.5),
        "huge magnitudes": noise * 1e30,
        "subnormal magnitudes": noise * 1e-40,
        "two scales (weights merge)": np.hstack([noise[:, :2048] * 1e-30, noise[:, 2048:] * 1e20]),
        "heavy tail": rng.exponential(size=(30, 4096)) ** 8,
        "half the row at the maximum": np.where(noise > 0, noise.max(), noise),
        "negative values only": -np.abs(noise) - 5.0,
        # a peak dequantized from uint8: few levels near the top, ties at the k-th value in most rows
        "quantized peaks": np.round(255 * np.exp(-(distance**2) / 50)) / 64,
        "infinities": np.where(rng.random((30, 4096)) < 0.01, np.inf, noise) * rng.choice([-1, 1], (30, 1)),
    }
