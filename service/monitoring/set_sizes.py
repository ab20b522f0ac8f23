"""Sizes of recent prediction sets, per nonconformity function, for the operators' plots: the drift
windows keep each set's shape entries, read as semi-major axis b and area pi a b (image px).
"""

from __future__ import annotations

from dataclasses import dataclass

import numpy as np

from service.conformal import NONCONFORMITY_SCORES, ellipse_axes

KINDS = tuple(NONCONFORMITY_SCORES)
QUANTILES = (0.05, 0.25, 0.5, 0.75, 0.95)
HISTOGRAM_BINS = 20


@dataclass(frozen=True)
class SizeSummary:
    quantiles: dict[str, float]  # "p05" ... "p95"
    histogram_edges: list[float]
    histogram_counts: list[int]


@dataclass(frozen=True)
class KindSizes:
    n: int
    unbounded: int  # sets reported as the whole plane (t = 0)
    semi_major_px: SizeSummary | None  # None when no bounded set was seen
    area_px2: SizeSummary | None


def shape_entries(shapes: np.ndarray) -> np.ndarray:
    """(M, 3): the distinct entries L00, L01, L11 of each shape matrix (what a window keeps)."""
    return shapes.reshape(-1, 4)[:, [0, 1, 3]]


def set_sizes(kinds: np.ndarray, entries: np.ndarray) -> dict[str, KindSizes]:
    """Sizes of the sets of every nonconformity function (``kinds``: index into KINDS, (M,))."""
    return {kind: _kind_sizes(entries[kinds == i]) for i, kind in enumerate(KINDS)}


def _kind_sizes(entries: np.ndarray) -> KindSizes:
    semi_minor, semi_major, _ = ellipse_axes(entries[:, [0, 1, 1, 2]].reshape(-1, 2, 2))
    bounded = np.isfinite(semi_major)
    area = np.pi * semi_minor[bounded] * semi_major[bounded]
    return KindSizes(
        n=len(entries),
        unbounded=int((~bounded).sum()),
        semi_major_px=_summary(semi_major[bounded]),
        area_px2=_summary(area),
    )


def _summary(values: np.ndarray) -> SizeSummary | None:
    if values.size == 0:
        return None
    counts, edges = np.histogram(values, bins=HISTOGRAM_BINS)
    quantiles = np.quantile(values, QUANTILES)
    named = {f"p{round(q * 100):02d}": float(v) for q, v in zip(QUANTILES, quantiles, strict=True)}
    return SizeSummary(quantiles=named, histogram_edges=edges.tolist(), histogram_counts=counts.tolist())
